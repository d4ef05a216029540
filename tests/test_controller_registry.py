"""A new controller kind is a class, a builder and one registration (pinnmpc.controller.registry): a toy controller
registered here, in the test alone, runs the real closed loop (the RK45 plant, metrics.json, trajectory.npz), touching
no project file."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf, open_dict

from pinnmpc.cli.structured import register_configs
from pinnmpc.controller.nmpc import StepStats
from pinnmpc.controller.registry import controller_kinds, register_controller, unregister_controller
from pinnmpc.simulation.run import run_closed_loop

CONF = Path(__file__).resolve().parents[1] / "conf"


@dataclass
class JointPD:
    """A joint-space PD law on the next reference sample, clipped to the input box: no model, no horizon to speak of."""

    low: np.ndarray
    high: np.ndarray
    kp: float
    kd: float
    horizon: int = 1
    stats: list[StepStats] = field(default_factory=list)

    def reset(self) -> None:
        """A new run: no statistics."""
        self.stats = []

    def make_step(self, x: np.ndarray, x_ref: np.ndarray) -> np.ndarray:
        """u = kp (q_ref - q) - kd v, within the box."""
        nq = len(self.low)
        u = self.kp * (x_ref[0, :nq] - x[:nq]) - self.kd * x[nq:]
        self.stats.append(StepStats(time_s=1e-6, iterations=1, cost=0.0, converged=True, fallback=False))
        return np.clip(u, self.low, self.high)

    def describe(self) -> dict[str, Any]:
        """For metrics.json."""
        return {"controller": "joint_pd", "solver": "none", "disturbance_gain": 0.0}


@pytest.fixture
def joint_pd() -> Iterator[str]:
    """The kind registered for one test, forgotten after it."""

    @register_controller("joint_pd")
    def build(cfg: Any, system: Any) -> tuple[JointPD, None, float]:
        """From the job's config: gains from controller.kp/kd, the system's input box."""
        box = system.input_box
        law = JointPD(np.array(box.low), np.array(box.high), float(cfg.controller.kp), float(cfg.controller.kd))
        return law, None, system.tau

    yield "joint_pd"
    unregister_controller("joint_pd")


def composed(*overrides: str) -> Any:
    """The closed-loop config of planar3 with the toy controller's settings in place of nmpc.yaml's."""
    register_configs()
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("closed_loop", overrides=["system=planar3", "progress=false", "plots=false", *overrides])
    toy = {"kind": "joint_pd", "kp": 60.0, "kd": 8.0, "horizon": 1, "u_low": None, "u_high": None}
    with open_dict(cfg):
        cfg.controller = OmegaConf.create({**toy, "Q": list(cfg.system.control.Q), "R": list(cfg.system.control.R)})
    return cfg


def test_a_registered_kind_runs_the_closed_loop(joint_pd: str, tmp_path: Path) -> None:
    assert controller_kinds()[:2] == ["pinn", "casadi"] and joint_pd in controller_kinds()
    m = run_closed_loop(composed("max_steps=40"), tmp_path)
    assert m["status"] == "ok" and m["steps"] == 40
    assert m["controller"] == "joint_pd" and m["solver"] == "none"
    positions = [v for k, v in m["mae"].items() if k.startswith("q_")]
    assert all(np.isfinite(v) and v < 1.0 for v in positions)  # a PD law on a 0.1 s hold: rough, but it follows
    moved = np.load(tmp_path / "trajectory.npz")["u"]
    assert np.abs(moved).max() > 1.0  # its inputs drove the plant
    assert (tmp_path / "metrics.json").is_file() and (tmp_path / "trajectory.npz").is_file()


def test_an_unknown_kind_names_the_registered_ones(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"controller.kind='joint_pd'; expected one of 'pinn', 'casadi'"):
        run_closed_loop(composed("max_steps=5"), tmp_path)


def test_a_kind_cannot_be_registered_twice(joint_pd: str) -> None:
    with pytest.raises(ValueError, match="controller kind 'joint_pd' is registered already"):
        register_controller(joint_pd)(lambda cfg, system: (None, None, 0.1))
    with pytest.raises(ValueError, match=r"controller kind 'no good': expected a name"):
        register_controller("no good")
