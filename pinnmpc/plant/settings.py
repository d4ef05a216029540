"""The plant settings (`plant=scipy` or `plant=mujoco`, key `plant`): structured configs whose fields, types and
defaults are the settings and whose field docstrings document them; the plants take their defaults from here."""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

from pinnmpc.util.checks import Check, check_settings, one_of, positive, real, whole

SCIPY_METHODS = ("RK45", "RK23", "DOP853", "Radau", "BDF", "LSODA")  # scipy.integrate.solve_ivp's methods


def _refuse(key: str, value: Any, expected: str) -> None:
    """One line naming the setting, its value and what was expected (the checks of several keys or of a kind)."""
    raise ValueError(f"plant.{key}={value!r}: expected {expected}")


MISMATCH_CHECKS: dict[str, Check] = {"friction_scale": real(0.0), "mass_scale": positive()}
SCIPY_CHECKS: dict[str, Check] = {
    "method": one_of(*SCIPY_METHODS),
    "rtol": positive(),
    "atol": positive(),
    "chatter_flips": lambda v, d: None if v is None else whole(1)(v, d),  # null: never redone
    "stick_slip_tighten": real(1.0),
    "max_switches": whole(1),
}
MUJOCO_CHECKS: dict[str, Check] = {
    "robot": lambda v, _d: None if v is None or isinstance(v, str) else "null or a name from system.robots",
    "substeps": whole(1),
}


@dataclass
class MismatchSettings:
    """What the plant changes in the model, the same for every plant."""

    friction_scale: float = 1.0
    """Plant-only scale of the modelled friction (or servo gain); 1.0: the model the network learned."""
    mass_scale: float = 1.0
    """Plant-only scale of every link's mass and inertia; 1.0: the model's (a MuJoCo robot's payload and armature
    are not scaled)."""

    def __post_init__(self) -> None:
        check_settings("plant", self, MISMATCH_CHECKS)


@dataclass
class ScipyPlantSettings(MismatchSettings):
    """`plant=scipy` (the default): scipy's solve_ivp on the true model over one zero-hold control period, as the
    paper (pinnmpc/plant/scipy_plant.py)."""

    kind: str = "scipy"
    """Which plant: scipy, or mujoco (a robot that is not the model: MujocoPlantSettings)."""
    method: str = "RK45"
    """solve_ivp's method (the paper's RK45)."""
    rtol: float = 1e-3
    """solve_ivp's rtol (scipy's default, as the paper)."""
    atol: float = 1e-6
    """solve_ivp's atol (scipy's default, as the paper)."""
    chatter_flips: int | None = 20
    """A step in which a sign(v) friction joint's velocity flips more often than this (the PowerCube's joint B at
    rest) is redone with the friction's switches located (stick-slip); null: never."""
    stick_slip_tighten: float = 100.0
    """... at rtol and atol divided by this: smooth between the switches, so closer to the exact solution than
    the chattering step, and still far cheaper."""
    max_switches: int = 1000
    """... with at most this many switches in one period, else the step fails."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.kind != "scipy":
            _refuse("kind", self.kind, "scipy with plant=scipy (choose the plant with plant=<kind>)")
        check_settings("plant", self, SCIPY_CHECKS)


@dataclass
class MujocoPlantSettings(MismatchSettings):
    """`plant=mujoco`: MuJoCo simulates the arm's URDF, nominal or as one of the system's robots (a payload, motor
    armature and dry friction the model lacks); URDF arms only (pinnmpc/plant/mujoco_robot.py)."""

    kind: str = "mujoco"
    """Which plant: mujoco, or scipy (the model itself: ScipyPlantSettings)."""
    robot: str | None = None
    """A name from system.robots (conf/system/<arm>.yaml, e.g. lab); null: the nominal model."""
    substeps: int = 50
    """Fixed RK4 steps per control period, the input held. At 50 one step lands closer to the exact flow than the
    scipy plant's RK45 (rtol 1e-3) on planar3 (h = 2 ms) and the Panda (h = 1 ms; its servo is stable up to
    h = 1.9 ms, and diverged at 20 substeps); tests/test_mujoco_plant.py."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.kind != "mujoco":
            _refuse("kind", self.kind, "mujoco with plant=mujoco (choose the plant with plant=<kind>)")
        check_settings("plant", self, MUJOCO_CHECKS)


PLANTS: dict[str, type[MismatchSettings]] = {"scipy": ScipyPlantSettings, "mujoco": MujocoPlantSettings}


def plant_settings(cfg: Any) -> ScipyPlantSettings | MujocoPlantSettings:
    """The checked settings of a plant config node (or dict) by its kind: a bad value is one line naming it."""
    values = dict(cfg.items()) if hasattr(cfg, "items") else dict(cfg)
    kind = values.get("kind", "scipy")
    if kind not in PLANTS:
        _refuse("kind", kind, f"one of {', '.join(PLANTS)} (conf/plant/)")
    cls = PLANTS[kind]
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise ValueError(f"plant.{unknown[0]}: not a setting of plant={kind}; expected one of {sorted(known)}")
    return cls(**values)  # type: ignore[return-value]


def register_configs() -> None:
    """Each plant's settings as the structured config behind conf/plant/<kind>.yaml (group schema/plant)."""
    from hydra.core.config_store import ConfigStore

    store = ConfigStore.instance()
    for name, cls in PLANTS.items():
        store.store(group="schema/plant", name=name, node=cls)
