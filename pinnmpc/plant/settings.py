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


def _per_joint(expected: str) -> Check:
    """A check of null or a list of positive numbers, one per joint, saying `expected` otherwise."""

    def check(v: Any, _d: Any) -> str | None:
        ok = v is None or (isinstance(v, (list, tuple)) and all(isinstance(g, (int, float)) and g > 0 for g in v))
        return None if ok else expected

    return check


FRANKA_CHECKS: dict[str, Check] = {
    "simulator": one_of("mujoco", "none"),
    "host": lambda v, _d: None if v is None or (isinstance(v, str) and v) else "null or a robot's address",
    "servo_gain": _per_joint("null or a list of positive gains, N m s/rad"),
    "initial_q": lambda v, _d: None if v is None or isinstance(v, (list, tuple)) else "null or joint angles, rad",
    "relative_dynamics_factor": positive(),
    "start_dynamics_factor": positive(),
    "hold_periods": positive(),
    "watchdog_periods": positive(),
    "limit_margin": real(0.0),
    "brake_acceleration": positive(),
    "start_timeout": positive(),
    "stall_timeout": positive(),
    "start_tolerance": positive(),
    "start_settle_speed": positive(),
    "start_settle_time": real(0.0),
    "rest_speed": positive(),
    "poll_s": positive(),
    "command_at": real(0.0),
    "velocity_limit": _per_joint("null or one positive speed per joint, rad/s"),
}


@dataclass
class FrankaPlantSettings(MismatchSettings):
    """`plant=franka`: a Franka arm through libfranka (franky), by default franky-sim's MuJoCo FR3 started on a
    free loopback address; `plant.simulator=none plant.host=<robot>` drives a real arm (pinnmpc/plant/franka.py,
    docs/franka.md)."""

    kind: str = "franka"
    """Which plant: franka (scipy, mujoco: the simulated models)."""
    simulator: str = "mujoco"
    """mujoco: start franky-sim (MuJoCo) for the run and stop it by its pid at the end; none: a robot is at host."""
    host: str | None = None
    """The robot's address (its FCI); with the simulator null picks a free 127.0.0.x (x >= 2)."""
    realtime_kernel: bool = False
    """Require a real-time kernel (libfranka's RealtimeConfig.Enforce): true for a real arm, as Franka asks."""
    servo_gain: list[float] | None = None
    """Joint velocity gains franky-sim is served with, N m s/rad; null: the system's servo_gain."""
    initial_q: list[float] | None = None
    """Where franky-sim's arm starts, rad; null: the middle of the joint limits."""
    relative_dynamics_factor: float = 1.0
    """franky's scale of its velocity, acceleration and jerk limits for the control period's motions (<= 1)."""
    move_to_start: bool = True
    """Move the arm to the reference's start before the loop (a jerk-limited joint motion)."""
    start_dynamics_factor: float = 0.2
    """... at this fraction of franky's limits: slow, for a first motion whose path nobody planned."""
    start_tolerance: float = 0.01
    """... and refuse to run when the arm stopped farther than this from the start, rad."""
    start_settle_speed: float = 1e-4
    """rad/s: when franky's move to the start ends the arm's own servo is still closing in on it (on franky-sim up to
    3 mrad off, at 0.05 rad/s); the loop begins once every joint is slower than this ..."""
    start_settle_time: float = 3.0
    """... or after this many s of robot time, wherever the arm is then (plant.start_tolerance still applies)."""
    hold_periods: float = 2.0
    """Each command is held this many periods, then the arm brakes by itself: the robot-side watchdog when this
    process stalls (a new command replaces the last long before)."""
    watchdog_periods: float = 1.0
    """Stop the arm and end the run when a command comes this many periods of robot time after its state."""
    limit_margin: float = 0.05
    """rad: the safety layer slows each joint so that it comes to rest this far inside its joint limits."""
    brake_acceleration: float = 2.0
    """rad/s^2 the slowing plans to brake with: well inside franky's joint acceleration limits (7.5-20 rad/s^2)."""
    start_timeout: float = 120.0
    """Wall seconds to wait for franky-sim to serve."""
    stall_timeout: float = 30.0
    """Wall seconds the robot's clock may stand still before the run ends as a plant failure."""
    rest_speed: float = 0.01
    """rad/s: the arm counts as at rest at the end when every joint is slower."""
    poll_s: float = 0.0005
    """Wall seconds between two reads of the robot's clock while a period runs."""
    record_fine: bool = False
    """Record the 1 kHz state stream within each period (collect sets it)."""
    command_at: float = 0.0
    """s of robot time after the state a command answers at which it is sent (a command ready sooner waits): the
    same dead time in every period, whatever the controller's wall time and franky-sim's speed; 0: sent at once;
    at most the control period, where each command goes out as the next period begins and the closed loop plans from
    the model's prediction of that period's start (delay compensation, docs/franka.md)."""

    velocity_limit: list[float] | None = None
    """rad/s per joint: the robot interface's joint velocity limits (franky refuses faster commands); every
    controller's input box is narrowed to them, and a robot that reports lower ones is refused at connect; null:
    franky's reported limits cap the safety layer alone."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.kind != "franka":
            _refuse("kind", self.kind, "franka with plant=franka (choose the plant with plant=<kind>)")
        if self.friction_scale != 1.0 or self.mass_scale != 1.0:
            _refuse("friction_scale", self.friction_scale, "1.0 with plant=franka (a robot is what it is)")
        check_settings("plant", self, FRANKA_CHECKS)

    def make_consistent(self) -> None:
        """The checks across fields, once all are set (a field alone is checked where it is declared)."""
        if self.simulator == "none" and not self.host:
            _refuse("host", self.host, "the robot's address with plant.simulator=none")


PLANTS: dict[str, type[MismatchSettings]] = {
    "scipy": ScipyPlantSettings,
    "mujoco": MujocoPlantSettings,
    "franka": FrankaPlantSettings,
}


def robot_name(plant: Any) -> str | None:
    """Which robot a plant config drives: a MuJoCo robot's name, franky-sim, or a Franka arm by its address."""
    if plant.get("kind") == "franka":
        return "franky-sim" if plant.get("simulator") != "none" else f"franka@{plant.get('host')}"
    return plant.get("robot")


def plant_settings(cfg: Any) -> ScipyPlantSettings | MujocoPlantSettings | FrankaPlantSettings:
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
