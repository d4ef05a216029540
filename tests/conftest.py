"""Shared fixtures: paths to ../shared (skipped when absent) and Hydra configs composed from conf/."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

from pinnmpc.cli.structured import register_configs

register_configs()  # the structured configs, before any test composes (the commands do the same)

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"
SHARED = ROOT.parent / "shared" / "powercube"


@pytest.fixture(autouse=True, scope="session")
def _one_thread() -> None:
    """Small tensors are fastest and most repeatable on one thread."""
    torch.set_num_threads(1)


@pytest.fixture(scope="session")
def golden() -> dict[str, np.ndarray]:
    """The golden vectors from ../shared, or skip."""
    path = SHARED / "golden.npz"
    if not path.is_file():
        pytest.skip(f"{path} is absent")
    return dict(np.load(path))


@pytest.fixture(scope="session")
def paper_reference_dir() -> Path:
    """The paper's reference folder from ../shared, or skip."""
    if not (SHARED / "reference" / "y_soll.mat").is_file():
        pytest.skip(f"{SHARED / 'reference'} is absent")
    return SHARED / "reference"


@pytest.fixture
def make_cfg() -> Callable[..., DictConfig]:
    """Compose a config from conf/ exactly as the CLI does, with overrides."""

    def _make(name: str, overrides: list[str] | None = None) -> DictConfig:
        with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
            return compose(config_name=name, overrides=overrides or [])

    return _make


TINY_TRAIN = [  # a real training run of a few seconds: tiny network, few points, no time budget
    "data.n_collocation=256",
    "data.n_data=16",
    "data.n_val=64",
    "data.val_h=1e-3",
    "data.n_anchor=32",
    "data.anchor_h=1e-3",
    "model.hidden=[16,16]",
    "model.auto_scale.samples=64",
    "model.auto_scale.h=1e-2",
    "module.lbfgs_max_iter=5",
    "trainer.max_time=null",
    "trainer.check_val_every_n_epoch=1",
    "trainer.enable_progress_bar=false",
    "trainer.enable_model_summary=false",
    "threads=1",
]


def check_substep_flow(prior: Any, x0: torch.Tensor, u: torch.Tensor, eps: float, atol: float) -> None:
    """A sub-stepped prior along t in [0, 1.07 tau] (training's t_max is past tau): it starts at x0, dq/dt = v at
    every t (each sub-step is the exact flow of its held torques), dx/dt is the central difference inside the
    sub-steps and the right-sided one at their boundaries (the held torques change there)."""
    b, n, h = x0.shape[0], x0.shape[-1] // 2, prior.arm.tau / prior.steps
    t = torch.linspace(0.0, 1.07 * prior.arm.tau, b, dtype=torch.float64).unsqueeze(-1)  # no point on a boundary
    t[: prior.steps + 1] = torch.arange(prior.steps + 1, dtype=torch.float64).unsqueeze(-1) * h  # the boundaries
    np.testing.assert_allclose(prior(0 * t, x0, u)[0].numpy(), x0.numpy(), atol=1e-14)
    x, dx = prior(t, x0, u)
    np.testing.assert_allclose(dx[:, :n].numpy(), x[:, n:].numpy(), rtol=1e-12, atol=1e-12)
    up, down = (prior(t + s, x0, u)[0] for s in (eps, -eps))
    edge = prior.steps + 1
    np.testing.assert_allclose(dx[edge:].numpy(), ((up - down) / (2 * eps))[edge:].numpy(), rtol=1e-6, atol=atol)
    right = prior(t + eps / 10, x0, u)[0]
    np.testing.assert_allclose(dx[:edge].numpy(), ((right - x) / (eps / 10))[:edge].numpy(), rtol=1e-4, atol=10 * atol)
    assert float((x - x0).abs().max()) > 1e-2  # it moves


def central_jacobian(
    flow: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], x0: torch.Tensor, u: torch.Tensor, eps: float = 1e-6
) -> torch.Tensor:
    """d flow(x0, u) / d(x0, u) (B, nx, nx + nu) by central differences: the reference an exact Jacobian is held to."""
    z, nx = torch.cat((x0, u), -1), x0.shape[-1]
    cols = []
    for k in range(z.shape[-1]):
        d = torch.zeros(z.shape[-1], dtype=z.dtype)
        d[k] = eps
        up, down = (flow((z + s * d)[:, :nx].clone(), (z + s * d)[:, nx:].clone()) for s in (1, -1))
        cols.append((up - down) / (2 * eps))
    return torch.stack(cols, -1)


def prior_misses(arm: Any, kinds: tuple[str, ...], x0: torch.Tensor, u: torch.Tensor) -> list[torch.Tensor]:
    """Per prior kind, its RMSE per state at tau against fine RK4 (h = 0.1 ms) on the points (x0, u)."""
    from pinnmpc.surrogate.prior import ArmPrior
    from pinnmpc.training.data import reference_flow

    t = torch.full((x0.shape[0], 1), arm.tau, dtype=torch.float64)
    true = reference_flow(arm, x0, u, arm.tau, 1e-4).double()
    return [(ArmPrior(arm, kind)(t, x0, u)[0] - true).square().mean(0).sqrt() for kind in kinds]


def check_compiled_prior(prior: Any, x0: torch.Tensor, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """A prior's controller C (value and Jacobian) against its torch form, its export (MX) against the C, and the
    torch Jacobian against central differences; returns the torch value and Jacobian at tau."""
    from pinnmpc.surrogate.casadi_network import prior_function

    tau = prior.arm.tau
    t = torch.full((x0.shape[0], 1), tau, dtype=torch.float64)
    x, jac = prior.with_jacobian(t, x0, u)
    xn, jn = prior.compiled(tau).with_jacobian(x0.numpy(), u.numpy())
    np.testing.assert_allclose(xn, x.numpy(), atol=1e-12)
    np.testing.assert_allclose(jn.reshape(jac.shape), jac.numpy(), atol=1e-10)
    exported = prior_function(prior, tau)
    for k in range(x0.shape[0]):
        np.testing.assert_allclose(np.asarray(exported(x0[k].numpy(), u[k].numpy())).ravel(), xn[k], atol=1e-12)
    numeric = central_jacobian(lambda a, b: prior(t, a, b)[0], x0, u)
    np.testing.assert_allclose(jac.numpy(), numeric.numpy(), atol=1e-6)
    return x, jac


def write_test_log(stem: Path, system: Any, robot: str, fine: int, coarse: list, fine_rows: list) -> str:
    """A log as `pinnmpc.collect` writes it from rows (t, x, u, episode) at the control rate and (t, x, episode) at
    `fine` samples per period; returns the .npz path."""
    from pinnmpc.robot_data.logs import RobotLog, write_log

    meta = {
        "system": system.name, "tau": system.tau, "robot": robot, "seed": 0, "noise_sigma": 0.0, "fine": fine,
        "state_names": list(system.state_names), "input_names": list(system.input_names),
        "robot_time_s": system.tau * sum(a[3] == b[3] for a, b in zip(coarse[:-1], coarse[1:])),  # its periods
    }  # fmt: skip
    columns = [np.array([row[i] for row in coarse]) for i in range(4)]
    log = RobotLog(*columns, *(np.array([row[i] for row in fine_rows]) for i in range(3)), meta)
    write_log(stem, log)
    return str(stem) + ".npz"
