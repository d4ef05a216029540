"""A new controller kind is a class, its settings and one registration (pinnmpc.controller.registry): a toy controller
registered here, in the test alone, runs the real closed loop (the RK45 plant, metrics.json, trajectory.npz) and the
bench, touching no project file."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf, open_dict

from pinnmpc.bench.run import run_bench
from pinnmpc.cli.structured import register_configs
from pinnmpc.controller.base import ControllerSettings, StepStats
from pinnmpc.controller.registry import controller_kinds, register_controller, unregister_controller
from pinnmpc.simulation.run import run_closed_loop
from pinnmpc.util import checks as c
from pinnmpc.util.checks import setting

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


@dataclass(kw_only=True)
class JointPDSettings(ControllerSettings):
    """The toy's settings: what every kind has, plus its gains (each checked where declared)."""

    kind: str = setting("joint_pd", check=c.one_of("joint_pd"))
    """This kind."""
    kp: float = setting(60.0, check=c.positive())
    """Proportional gain, N m/rad."""
    kd: float = setting(8.0, check=c.real(0.0))
    """Derivative gain, N m s/rad."""


@pytest.fixture
def joint_pd() -> Iterator[str]:
    """The kind registered for one test, forgotten after it."""

    @register_controller("joint_pd", JointPDSettings)
    def build(settings: JointPDSettings, cfg: Any, system: Any) -> tuple[JointPD, None, float]:
        """From its checked settings: the gains, the system's input box."""
        box = system.input_box
        return JointPD(np.array(box.low), np.array(box.high), settings.kp, settings.kd), None, system.tau

    yield "joint_pd"
    unregister_controller("joint_pd")


def composed(*overrides: str) -> Any:
    """The closed-loop config of planar3 with the toy controller's settings in place of nmpc.yaml's."""
    register_configs()
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("closed_loop", overrides=["system=planar3", "progress=false", "plots=false", *overrides])
    toy = {"kind": "joint_pd", "kp": 60.0, "horizon": 1}  # kd: its default
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
        register_controller(joint_pd, JointPDSettings)(lambda settings, cfg, system: (None, None, 0.1))
    with pytest.raises(ValueError, match=r"controller kind 'no good': expected a name"):
        register_controller("no good", JointPDSettings)
    with pytest.raises(ValueError, match=r"controller kind 'pd2': settings .*expected a ControllerSettings subclass"):
        register_controller("pd2", dict)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    "key, value, expected",
    [
        ("kp", -1.0, r"controller.kp=-1.0: expected a finite number > 0"),
        ("kpp", 1.0, r"controller.kpp: not a setting here; expected one of \[.*'kd'.*\]"),
        ("horizon", 0, r"controller.horizon=0: expected a whole number >= 1"),
    ],
)
def test_its_settings_are_checked_where_declared(joint_pd: str, tmp_path: Path, key: str, value: Any, expected) -> None:
    cfg = composed("max_steps=5")
    with open_dict(cfg):
        cfg.controller[key] = value
    with pytest.raises(ValueError, match=expected):
        run_closed_loop(cfg, tmp_path)
    assert not (tmp_path / "metrics.json").exists()


def test_the_bench_lists_every_kind_and_runs_the_new_one(joint_pd: str, tmp_path: Path) -> None:
    """Section 8: the built-in kinds listed with their sections, the toy run on the bench's reference and plant."""
    register_configs()
    off = [f"{s}.enabled=false" for s in ("step", "closed_loop", "optimality", "scaling", "classical")]
    overrides = ["system=planar3", "progress=false", "plots=false", "closed_loop.max_steps=30", *off]
    overrides.append("peers.enabled=false")
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("bench", overrides=[*overrides, "+kinds.settings.joint_pd.kd=6.0"])
    result = run_bench(cfg, tmp_path)
    rows = result["kinds"]["rows"]
    assert list(rows)[:2] == ["pinn", "casadi"] and rows["pinn"] == {"section": "closed_loop", "ran": False}
    toy = rows[joint_pd]
    assert toy["status"] == "ok" and toy["steps"] == 30 and toy["solver"] == "none"
    assert all(np.isfinite(v) for v in toy["mae"].values())
    assert "| joint_pd | ok |" in (tmp_path / "bench.md").read_text()
