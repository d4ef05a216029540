"""Dense self-scaled BFGS: exact on quadratics, a Rosenbrock valley, small checkpoints, and real training with it."""

from __future__ import annotations

import lightning as L
import pytest
import torch

from pinnmpc.surrogate.network import PINN
from pinnmpc.systems import PowerCube
from pinnmpc.training.data import CollocationDataModule
from pinnmpc.training.module import PINNModule
from pinnmpc.training.run import train
from pinnmpc.training.ssbfgs import SSBFGS, InverseHessian, Step
from tests.conftest import TINY_TRAIN


def _minimise(f, x0: torch.Tensor, **kwargs) -> tuple[torch.Tensor, SSBFGS]:
    """Run one SSBFGS step (max_iter iterations) on f from x0."""
    x = torch.nn.Parameter(x0.clone())
    opt = SSBFGS([x], **kwargs)

    def closure() -> torch.Tensor:
        opt.zero_grad()
        loss = f(x)
        loss.backward()
        return loss

    opt.step(closure)
    return x.detach(), opt


@pytest.mark.parametrize("variant", ["ssbfgs", "ssbroyden", "bfgs"])
def test_a_convex_quadratic_is_solved_and_h_stays_positive_definite(variant):
    g = torch.Generator().manual_seed(0)
    a = torch.randn(8, 8, generator=g, dtype=torch.float64)
    A = a @ a.T + 0.5 * torch.eye(8, dtype=torch.float64)
    b = torch.randn(8, generator=g, dtype=torch.float64)
    x, opt = _minimise(lambda x: 0.5 * x @ A @ x - b @ x, torch.zeros(8, dtype=torch.float64), max_iter=60,
                       variant=variant)  # fmt: skip
    assert torch.allclose(x, torch.linalg.solve(A, b), atol=1e-7)
    H = opt.state[opt._params[0]]["H"].matrix()
    assert torch.allclose(H, H.T, atol=1e-12) and torch.linalg.eigvalsh(H).min() > 0  # updates keep H SPD


def test_updates_kept_aside_give_the_iterates_of_updates_applied_at_once():
    g = torch.Generator().manual_seed(1)
    a = torch.randn(30, 30, generator=g, dtype=torch.float64)
    A, b = a @ a.T + 0.1 * torch.eye(30, dtype=torch.float64), torch.randn(30, generator=g, dtype=torch.float64)
    x0 = torch.zeros(30, dtype=torch.float64)
    at_once, eager = _minimise(lambda x: 0.5 * x @ A @ x - b @ x, x0, max_iter=17, buffer=1)
    kept, lazy = _minimise(lambda x: 0.5 * x @ A @ x - b @ x, x0, max_iter=17, buffer=5)
    assert lazy.state[lazy._params[0]]["H"].B.shape[1] > 0  # some updates still pending at the end
    assert torch.allclose(at_once, kept, rtol=0, atol=1e-9)
    H_eager, H_lazy = (o.state[o._params[0]]["H"].matrix() for o in (eager, lazy))
    assert torch.allclose(H_eager, H_lazy, rtol=0, atol=1e-9)


@pytest.mark.parametrize("variant", ["ssbfgs", "ssbroyden", "bfgs"])
@pytest.mark.parametrize("first", [True, False])
def test_an_update_keeps_the_secant_equation_and_h_positive_definite(variant, first):
    g = torch.Generator().manual_seed(2)
    n = 12
    opt = SSBFGS([torch.nn.Parameter(torch.zeros(n, dtype=torch.float64))], variant=variant, hessian_dtype="float64")
    for trial in range(20):  # random SPD H and pairs with y's > 0, a step along -H g as the optimiser takes
        a = torch.randn(n, n, generator=g, dtype=torch.float64)
        H = InverseHessian(n, 1.0, torch.float64, torch.device("cpu"), buffer=4)
        H.D = a @ a.T / n + 0.1 * torch.eye(n, dtype=torch.float64)
        grad, t = torch.randn(n, generator=g, dtype=torch.float64), 0.3 + trial / 10
        s = -t * (H @ grad)
        y = torch.linalg.solve(H.D, s) * (0.2 + trial / 5) + 0.05 * torch.randn(n, generator=g, dtype=torch.float64)
        if float(y @ s) <= 0:
            continue
        slope = -float(grad @ s)
        step = Step(s=s, y=y, hy=H @ y, slope=slope, sbs=t * slope, first=first)
        opt._update(H, step)
        new = H.matrix()
        assert torch.allclose(new @ y, s, rtol=1e-9, atol=1e-11)  # H+ y = s for every member of the family
        assert torch.allclose(new, new.T) and torch.linalg.eigvalsh(new).min() > 0


def test_the_rosenbrock_valley_is_followed_to_its_minimum():
    def rosenbrock(x: torch.Tensor) -> torch.Tensor:
        return ((1 - x[0::2]) ** 2 + 100 * (x[1::2] - x[0::2] ** 2) ** 2).sum()

    x, opt = _minimise(rosenbrock, torch.tensor([-1.2, 1.0] * 4, dtype=torch.float64), max_iter=300)
    assert torch.allclose(x, torch.ones(8, dtype=torch.float64), atol=1e-5)
    assert opt.state[opt._params[0]]["func_evals"] < 600


def test_checkpoints_leave_the_dense_matrix_out_and_a_reset_forgets_it():
    x, opt = _minimise(lambda x: (x * x).sum() + x.sum() ** 4, torch.ones(50, dtype=torch.float64), max_iter=5)
    state = opt.state[opt._params[0]]
    assert state["H"].matrix().shape == (50, 50)
    saved = opt.state_dict()["state"][0]
    assert "H" not in saved and saved["n_iter"] == state["n_iter"]
    opt.reset()
    assert "H" not in opt.state[opt._params[0]]


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [({"variant": "sr1"}, "ssbfgs_variant='sr1'"), ({"hessian_dtype": "half"}, "hessian_dtype='half'"),
     ({"max_params": 10}, "50 x 50 inverse Hessian"), ({"buffer": 0}, "hessian_buffer=0")],
)  # fmt: skip
def test_bad_settings_are_refused_with_the_setting_named(kwargs, match):
    with pytest.raises(ValueError, match=match):
        SSBFGS([torch.nn.Parameter(torch.zeros(50))], **kwargs)


def test_training_with_ssbfgs_lowers_the_loss(tmp_path):
    system = PowerCube()
    model = PINN(system.state_box.low, system.state_box.high, system.input_box.low, system.input_box.high,
                 t_max=0.25, hidden=[16, 16], activation="silu", ic="gated", time_basis=[0.02, 0.045])  # fmt: skip
    sizes = dict(n_collocation=256, n_data=16, n_val=64, val_h=1e-3, resample_every=0, n_anchor=0)
    dm = CollocationDataModule(system, tau=0.2, t_max=0.25, **sizes)
    module = PINNModule(system, model, tau=0.2, lbfgs_max_iter=5, optimizer="ssbfgs", kinematic_weight=1.0)
    dm.setup()
    before = float(module.losses(dm.batch)["total"].detach())
    trainer = L.Trainer(max_epochs=3, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, default_root_dir=tmp_path, num_sanity_val_steps=0)  # fmt: skip
    trainer.fit(module, datamodule=dm)
    assert float(module.losses(dm.batch)["total"].detach()) < 0.5 * before


def test_a_run_with_ssbfgs_checkpoints_without_the_matrix_and_resumes(make_cfg, tmp_path):
    overrides = [*TINY_TRAIN, "module.optimizer=ssbfgs", "trainer.max_epochs=2"]
    assert train(make_cfg("train", overrides), tmp_path)["status"] == "ok"
    state = torch.load(tmp_path / "checkpoints" / "last.ckpt", weights_only=False)["optimizer_states"][0]["state"][0]
    assert "H" not in state and state["n_iter"] > 0
    before = {f: f.stat().st_mtime_ns for f in tmp_path.rglob("*") if f.is_file()}
    with pytest.raises(ValueError, match="trained with module.optimizer=ssbfgs, this configuration has .*=lbfgs"):
        other = [*overrides, "module.optimizer=lbfgs", "trainer.max_epochs=4", "resume=true"]
        train(make_cfg("train", other), tmp_path)
    with pytest.raises(ValueError, match="holds a training run .*expected resume=true to continue it"):
        train(make_cfg("train", [*overrides, "trainer.max_epochs=4"]), tmp_path)  # a fresh run over it
    assert before == {f: f.stat().st_mtime_ns for f in tmp_path.rglob("*") if f.is_file()}  # nothing touched
    resumed = train(make_cfg("train", [*overrides, "trainer.max_epochs=4", "resume=true"]), tmp_path)
    assert resumed["epochs"] == 4 and resumed["status"] == "ok"


def test_an_unknown_optimizer_is_refused():
    system = PowerCube()
    model = PINN(system.state_box.low, system.state_box.high, system.input_box.low, system.input_box.high,
                 t_max=0.25, hidden=[8], activation="silu", ic="hard")  # fmt: skip
    with pytest.raises(ValueError, match="module.optimizer='adamw'"):
        PINNModule(system, model, tau=0.2, optimizer="adamw")


def test_trial_steps_into_overflow_are_shortened_not_taken():
    def nan_beyond_ten(x: torch.Tensor) -> torch.Tensor:  # a network that overflows for far-off parameters
        loss = ((x - 3.0) ** 2).sum() + 0.1 * (x**4).sum()
        return torch.where(x.abs().max() > 10, torch.full_like(loss, float("nan")), loss)

    x, opt = _minimise(nan_beyond_ten, torch.zeros(6, dtype=torch.float64), max_iter=50, lr=100.0)
    assert torch.isfinite(x).all() and float(nan_beyond_ten(x)) < float(nan_beyond_ten(torch.full((6,), 2.0)))
    assert "H" in opt.state[opt._params[0]]
