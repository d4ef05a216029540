"""What a robot has that the nominal model does not: one schema (RobotEffects), its check (robot_effects) and the law of
the effects MuJoCo has no joint attribute for (EffectLaw), which the MuJoCo plant applies as joint force.

Effects in the identification's class (pinnmpc.robot_data.identify fits them): a tip payload, motor armature and dry
friction (MuJoCo's frictionloss). Effects outside it, applied here at every RK4 stage:

- Stribeck friction: stribeck * exp(-(v / stribeck_speed)^2) on top of the dry friction (static above Coulomb);
- load-dependent friction: load_friction * |tau_motor| (a gear's friction grows with the torque it carries);
- torque-speed droop: the motor's torque times max(0, 1 - |v| / droop_speed);
- cogging: cogging * sin(2 pi q / cogging_period), a torque fixed to the rotor's position;
- actuator lag: the input reaches the actuator through a first-order filter with time constant lag (s), a state the
  plant carries from one period to the next.

Each friction's direction is tanh(slip_slope v), smooth as the model's Coulomb term.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import Field, dataclass, field, fields
from typing import Any

import numpy as np

PAYLOAD_KEYS = ("mass", "pos")


def _joint(unit: str, attribute: str | None = None) -> Any:
    """A per-joint effect (one number >= 0 per joint; none: all zero), set as a MuJoCo joint attribute or applied by
    EffectLaw."""
    meta = {"unit": unit, "per_joint": True, **({"joint_attribute": attribute} if attribute else {})}
    return field(default=(), metadata=meta)


def _scalar(default: float, unit: str, positive: bool = False) -> Any:
    """One number >= 0 (> 0 where positive) for the whole arm."""
    return field(default=default, metadata={"unit": unit, "positive": positive})


@dataclass(frozen=True)
class RobotEffects:
    """A validated robot description (system.robots.<name>): a new effect is one field here and its use in
    compile_arm (a joint attribute) or EffectLaw (an applied force)."""

    payload_mass: float = 0.0  # kg, a point mass fixed to the tip
    payload_pos: tuple[float, float, float] | None = None  # m, in the tip frame (None: the tip itself)
    armature: tuple[float, ...] = _joint("kg m^2", "armature")
    """per joint, added to the mass matrix diagonal (rotor inertia)"""
    frictionloss: tuple[float, ...] = _joint("N m", "frictionloss")
    """per joint, MuJoCo's dry friction (a soft constraint)"""
    stribeck: tuple[float, ...] = _joint("N m")
    """per joint, friction above the dry friction at rest, fading with speed (Stribeck)"""
    stribeck_speed: float = _scalar(0.1, "rad/s", positive=True)
    """the speed over which the Stribeck friction fades (exp(-(v / stribeck_speed)^2))"""
    load_friction: tuple[float, ...] = _joint("1")
    """per joint, friction as a fraction of the torque the motor delivers (a gear's load-dependent loss)"""
    droop_speed: tuple[float, ...] = _joint("rad/s")
    """per joint, the speed at which the motor's torque has fallen to zero, linearly (0: no droop)"""
    cogging: tuple[float, ...] = _joint("N m")
    """per joint, the amplitude of a torque fixed to the rotor's position"""
    cogging_period: float = _scalar(0.2, "rad", positive=True)
    """the angle over which the cogging torque repeats"""
    lag: float = _scalar(0.0, "s")
    """time constant of a first-order filter between the input and the actuator (0: none)"""
    slip_slope: float = _scalar(50.0, "s/rad", positive=True)
    """tanh(slip_slope v): the direction of the applied frictions, smoothed"""

    @property
    def applied(self) -> bool:
        """Whether any effect needs EffectLaw (MuJoCo's attributes hold the rest)."""
        return bool(self.lag) or any(any(getattr(self, f.name)) for f in applied_joint_effects())


NOMINAL = RobotEffects()  # the nominal model: no effect


def per_joint_effects() -> tuple[Field, ...]:
    """RobotEffects' per-joint fields."""
    return tuple(f for f in fields(RobotEffects) if f.metadata.get("per_joint"))


def attribute_effects() -> tuple[Field, ...]:
    """The per-joint fields MuJoCo sets as joint attributes."""
    return tuple(f for f in per_joint_effects() if "joint_attribute" in f.metadata)


def applied_joint_effects() -> tuple[Field, ...]:
    """The per-joint fields EffectLaw applies as force."""
    return tuple(f for f in per_joint_effects() if "joint_attribute" not in f.metadata)


def scalar_effects() -> tuple[Field, ...]:
    """RobotEffects' whole-arm numbers (not the payload's)."""
    return tuple(f for f in fields(RobotEffects) if "positive" in f.metadata)


ROBOT_KEYS = ("payload", *(f.name for f in per_joint_effects()), *(f.name for f in scalar_effects()))


def _plain(value: Any) -> Any:
    """Nested mappings and sequences (OmegaConf nodes, numpy arrays included) as dicts and lists."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, Sequence) and not isinstance(value, str | bytes):
        return [_plain(v) for v in value]
    return value


def _number(key: str, value: Any, unit: str, positive: bool = False) -> float:
    """One finite number >= 0 (> 0), or a one-line error naming the key."""
    bad = isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value)
    if bad or value < 0 or (positive and value == 0):
        raise ValueError(f"robot {key}={value!r}; expected a finite number {'>' if positive else '>='} 0 ({unit})")
    return float(value)


def _per_joint(key: str, value: Any, joints: Sequence[str], unit: str) -> tuple[float, ...]:
    """One finite number >= 0 per joint, or a one-line error naming the key."""
    n = len(joints)
    ok = isinstance(value, list) and len(value) == n
    ok = ok and all(not isinstance(v, bool) and isinstance(v, int | float) and math.isfinite(v) for v in value)
    if not ok or any(v < 0 for v in value):
        raise ValueError(
            f"robot {key}={value!r}; expected {n} finite numbers >= 0 ({unit}), one per joint {list(joints)}"
        )
    return tuple(float(v) for v in value)


def robot_effects(robot: Mapping[str, Any] | None, joints: Sequence[str]) -> RobotEffects:
    """Check a robot description (None: the nominal model) before anything is compiled."""
    if robot is None:
        return RobotEffects()
    robot = _plain(robot)
    if not isinstance(robot, dict):
        raise ValueError(f"robot={robot!r}; expected a mapping with some of {list(ROBOT_KEYS)}")
    unknown = [k for k in robot if k not in ROBOT_KEYS]
    if unknown:
        raise ValueError(f"robot keys {unknown}; expected some of {list(ROBOT_KEYS)}")
    n = len(joints)
    effects: dict[str, Any] = {}
    for f in per_joint_effects():
        value = robot.get(f.name)
        effects[f.name] = (0.0,) * n if value is None else _per_joint(f.name, value, joints, f.metadata["unit"])
    for f in scalar_effects():
        if robot.get(f.name) is not None:
            effects[f.name] = _number(f.name, robot[f.name], f.metadata["unit"], f.metadata["positive"])
    payload = robot.get("payload")
    if payload is not None:
        if not isinstance(payload, dict) or "mass" not in payload or any(k not in PAYLOAD_KEYS for k in payload):
            raise ValueError(f"robot payload={payload!r}; expected {{mass: kg, pos: [x, y, z] m in the tip frame}}")
        effects["payload_mass"] = _number("payload.mass", payload["mass"], "kg")
        pos = payload.get("pos")
        if pos is not None:
            ok = isinstance(pos, list) and len(pos) == 3
            ok = ok and all(not isinstance(v, bool) and isinstance(v, int | float) and math.isfinite(v) for v in pos)
            if not ok:
                raise ValueError(f"robot payload.pos={pos!r}; expected 3 finite numbers (m, in the tip frame)")
            effects["payload_pos"] = tuple(float(v) for v in pos)
    return RobotEffects(**effects)


class EffectLaw:
    """The applied effects of a robot as joint force, vectorised over joints (and any leading batch dimensions)."""

    def __init__(self, effects: RobotEffects) -> None:
        self.effects = effects
        e = effects
        self.stribeck, self.load = np.asarray(e.stribeck, float), np.asarray(e.load_friction, float)
        droop = np.asarray(e.droop_speed, float)
        self.inv_droop = np.divide(1.0, droop, out=np.zeros_like(droop), where=droop > 0)
        self.cogging, self.wave = np.asarray(e.cogging, float), 2.0 * math.pi / e.cogging_period
        self.inv_vs2, self.slope = 1.0 / e.stribeck_speed**2, e.slip_slope

    def delivered(self, v: np.ndarray, motor: np.ndarray) -> np.ndarray:
        """The motor's torque after its torque-speed droop."""
        return motor * np.clip(1.0 - np.abs(v) * self.inv_droop, 0.0, 1.0) if self.inv_droop.any() else motor

    def resisting(self, q: np.ndarray, v: np.ndarray, delivered: np.ndarray) -> np.ndarray:
        """Stribeck and load-dependent friction (against v) plus cogging: the joint force the arm loses."""
        level = self.stribeck * np.exp(-(v * v) * self.inv_vs2) + self.load * np.abs(delivered)
        return level * np.tanh(self.slope * v) + self.cogging * np.sin(self.wave * q)

    def joint_force(self, q: np.ndarray, v: np.ndarray, motor: np.ndarray) -> np.ndarray:
        """What reaches the joint of the motor's torque (motor: the actuation law's torque at the lagged input)."""
        delivered = self.delivered(v, motor)
        return delivered - self.resisting(q, v, delivered)

    def needed_motor(self, q: np.ndarray, v: np.ndarray, joint: np.ndarray) -> np.ndarray:
        """The motor torque whose joint force is `joint` (the inverse of joint_force, for sizing a robot): the
        friction's load term is taken at the sign of the torque needed."""
        need = joint + self.stribeck * np.exp(-(v * v) * self.inv_vs2) * np.tanh(self.slope * v)
        need = need + self.cogging * np.sin(self.wave * q)
        scale = 1.0 - self.load * np.sign(need) * np.tanh(self.slope * v)
        delivered = need / scale
        factor = np.clip(1.0 - np.abs(v) * self.inv_droop, 0.0, 1.0) if self.inv_droop.any() else 1.0
        with np.errstate(divide="ignore"):
            return np.where(factor > 0, delivered / factor, np.inf * np.sign(delivered))
