"""A robot that is not the model: MuJoCo compiles the arm's URDF, optionally with effects the model lacks.

The controller and the surrogate know the URDF's rigid bodies and the system's actuation law. This plant simulates
them in another engine (MuJoCo instead of Pinocchio/adam), and a named robot (conf/system/<arm>.yaml, `robots`) adds
what the nominal model leaves out: a payload at the tip, motor armature and dry joint friction. Only this module reads
a robot's description. Each period holds the input and integrates by explicit RK4 at a fixed step around
`mujoco.mj_forward`, applying the system's actuation law at every stage; the velocity servo compensates the gravity
of the nominal arm it was tuned on, so a payload's weight is a real mismatch.
"""

from __future__ import annotations

import math
import time
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from dataclasses import Field, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from pinnmpc.plant.scipy_plant import PlantError
from pinnmpc.plant.settings import MujocoPlantSettings
from pinnmpc.systems import RigidArm
from pinnmpc.systems.urdf import locked_urdf

PAYLOAD_KEYS = ("mass", "pos")
PAYLOAD_BODY = "pinnmpc_payload"  # the point mass's body in the compiled model


@dataclass(frozen=True)
class RobotEffects:
    """A validated robot description: what the physical arm has that the nominal model does not. A per-joint effect
    is one field whose metadata names its unit and the MuJoCo joint attribute it sets: robot_effects checks it and
    compile_arm applies it from there."""

    payload_mass: float = 0.0  # kg, a point mass fixed to the tip
    payload_pos: tuple[float, float, float] | None = None  # m, in the tip frame (None: the tip itself)
    armature: tuple[float, ...] = field(default=(), metadata={"unit": "kg m^2", "joint_attribute": "armature"})
    """per joint, added to the mass matrix diagonal (rotor inertia)"""
    frictionloss: tuple[float, ...] = field(default=(), metadata={"unit": "N m", "joint_attribute": "frictionloss"})
    """per joint, MuJoCo's dry friction (a soft constraint)"""


def per_joint_effects() -> tuple[Field, ...]:
    """RobotEffects' per-joint fields (those with a joint attribute)."""
    return tuple(f for f in fields(RobotEffects) if "joint_attribute" in f.metadata)


ROBOT_KEYS = ("payload", *(f.name for f in per_joint_effects()))  # what a robot description may name


def _import_mujoco() -> Any:
    """MuJoCo on first use, so the package imports without it; its absence is said in one line."""
    try:
        import mujoco
    except ImportError:
        raise ModuleNotFoundError("plant=mujoco needs the mujoco package: pip install mujoco") from None
    return mujoco


def _plain(value: Any) -> Any:
    """Nested mappings and sequences (OmegaConf nodes, numpy arrays included) as dicts and lists, so checks see one
    type."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, Sequence) and not isinstance(value, str | bytes):
        return [_plain(v) for v in value]
    return value


def _number(key: str, value: Any, unit: str) -> float:
    """One finite number >= 0, or a one-line error naming the key."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) or value < 0:
        raise ValueError(f"robot {key}={value!r}; expected a finite number >= 0 ({unit})")
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


def _mjcf_urdf(system: RigidArm) -> tuple[str, str]:
    """The locked URDF without geometry (no mesh files needed) plus MuJoCo's compiler options to read its inertias
    as written, and the link the last joint moves."""
    root = ET.fromstring(locked_urdf(Path(system.urdf), system.joints))
    for link in root.iter("link"):
        for tag in ("visual", "collision"):
            for element in link.findall(tag):
                link.remove(element)
    options = {
        "inertiafromgeom": "false",
        "balanceinertia": "false",
        "discardvisual": "true",
        "fusestatic": "false",  # keeps every link a body: the tip frame stays addressable
        "boundmass": "0",
        "boundinertia": "0",
    }
    ET.SubElement(ET.SubElement(root, "mujoco"), "compiler", options)
    last = next(j for j in root.findall("joint") if j.get("name") == system.joints[-1])
    return ET.tostring(root, encoding="unicode"), last.find("child").get("link")


def _tip_body(system: RigidArm, root_text: str, last_link: str) -> str:
    """The body of the tip frame: system.tip_frame (a link, or a joint's child link) or the last moved link."""
    if not system.tip_frame:
        return last_link
    root = ET.fromstring(root_text)
    if any(link.get("name") == system.tip_frame for link in root.iter("link")):
        return system.tip_frame
    for joint in root.findall("joint"):
        if joint.get("name") == system.tip_frame:
            return joint.find("child").get("link")
    raise ValueError(f"{system.name}: tip_frame={system.tip_frame!r} is neither a link nor a joint of {system.urdf}")


def compile_arm(system: RigidArm, effects: RobotEffects = RobotEffects()) -> Any:
    """The arm as a mujoco.MjModel: URDF inertias as written (scaled by system.mass_scale), gravity from the system,
    no contacts, limits, damping or springs; the robot's payload, armature and frictionloss on top."""
    if getattr(system, "payload", None) or getattr(system, "armature", None):
        raise ValueError(
            f"system {system.name} models a payload or armature; expected plant=mujoco on an arm without them "
            "(describe a robot's payload and armature under system.robots, plant.robot=<name>)"
        )
    mujoco = _import_mujoco()
    text, last_link = _mjcf_urdf(system)
    spec = mujoco.MjSpec.from_string(text)
    spec.option.gravity = np.asarray(system.gravity, dtype=np.float64)
    spec.option.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT | mujoco.mjtDisableBit.mjDSBL_LIMIT
    spec.option.tolerance = 1e-12  # the friction constraint's solve: converged far below the integration error
    spec.option.iterations = 200
    for body in spec.bodies:
        if system.mass_scale != 1.0:
            body.mass *= system.mass_scale
            body.inertia = np.asarray(body.inertia) * system.mass_scale
            body.fullinertia = np.asarray(body.fullinertia) * system.mass_scale
    by_name = {j.name: j for j in spec.joints}
    for j in spec.joints:  # the URDF's <dynamics> and <limit> tags are read by MuJoCo: the law lives in the system
        j.damping, j.stiffness = np.zeros_like(j.damping), np.zeros_like(j.stiffness)
        j.frictionloss, j.armature = 0.0, 0.0
        j.limited = mujoco.mjtLimited.mjLIMITED_FALSE
        j.actfrclimited = mujoco.mjtLimited.mjLIMITED_FALSE
    for f in per_joint_effects():
        values = getattr(effects, f.name)
        for i, name in enumerate(system.joints if values else ()):
            setattr(by_name[name], f.metadata["joint_attribute"], values[i])
    if effects.payload_mass > 0:
        tip = _tip_body(system, text, last_link)
        parent = spec.body(tip)
        if effects.payload_pos is not None:
            pos = np.asarray(effects.payload_pos)
        elif tip == last_link and not system.tip_frame:  # the tip pinnmpc draws: twice the link's centre of mass
            pos = 2.0 * np.asarray(parent.ipos)
        else:
            pos = np.zeros(3)
        parent.add_body(  # a point mass: inertia about its own centre 0, all of it from the offset
            name=PAYLOAD_BODY,
            pos=pos,
            ipos=np.zeros(3),
            mass=effects.payload_mass,
            inertia=np.zeros(3),
            explicitinertial=True,
        )
    return spec.compile()


@dataclass
class MujocoPlant:
    """Zero-hold plant x_{k+1} = flow(x_k, u_k, tau): fixed-step RK4 around mujoco.mj_forward, on the nominal arm
    (robot None) or a robot with effects the model lacks (`robot_effects`)."""

    system: RigidArm
    tau: float
    robot: Mapping[str, Any] | None = None  # None: the nominal model; else {payload, armature, frictionloss}
    substeps: int = MujocoPlantSettings.substeps  # RK4 steps per control period (pinnmpc/plant/settings.py)
    step_times: list[float] = field(default_factory=list)
    stick_slip_steps: int = 0  # no stick-slip redo here: kept so callers read every plant alike

    def __post_init__(self) -> None:
        mujoco = _import_mujoco()
        if not isinstance(self.system, RigidArm):
            raise ValueError(f"plant=mujoco needs a URDF arm (pinnmpc.systems.RigidArm), got {type(self.system)}")
        if not self.tau > 0:
            raise ValueError(f"plant tau must be > 0, got {self.tau}")
        if isinstance(self.substeps, bool) or not isinstance(self.substeps, int) or self.substeps < 1:
            raise ValueError(f"plant substeps={self.substeps!r}; expected an integer >= 1")
        self.effects = robot_effects(self.robot, self.system.joints)
        self.model = compile_arm(self.system, self.effects)
        self.model.opt.timestep = self.tau / self.substeps  # soft constraints (frictionloss) act no faster
        #   than two of MuJoCo's steps: tell it the step RK4 takes
        self.data = mujoco.MjData(self.model)
        ids = [mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_JOINT, j) for j in self.system.joints]
        qadr, dadr = self.model.jnt_qposadr[ids], self.model.jnt_dofadr[ids]
        n = self.system.nq
        if self.model.nq != n or self.model.nv != n:
            raise ValueError(f"{self.system.name}: MuJoCo compiled {self.model.nv} joints; expected {n}")
        same = np.array_equal(qadr, np.arange(n)) and np.array_equal(dadr, np.arange(n))
        self._qadr, self._dadr = (slice(None), slice(None)) if same else (qadr, dadr)
        self._servo = self.system.actuation == "velocity_servo"
        if self._servo:  # the servo's gravity compensation: the nominal arm's, computed in its own data
            self._servo_model = compile_arm(self.system) if self.robot is not None else self.model
            self._servo_data = mujoco.MjData(self._servo_model)  # its qvel stays 0: its bias force is gravity alone
            self._gravity_out = np.empty(n)
        d = self.data  # views into MjData, bound once: the stage function runs 4 substeps times per period
        self._qpos, self._qvel, self._qfrc, self._qacc = d.qpos, d.qvel, d.qfrc_applied, d.qacc
        self._forward = mujoco.mj_forward
        self._mujoco = mujoco

    def _gravity(self, q: np.ndarray) -> np.ndarray:
        """g(q) of the nominal arm (mass-scaled as the system): what its velocity servo compensates."""
        mj, m, d, out = self._mujoco, self._servo_model, self._servo_data, self._gravity_out
        d.qpos[self._qadr] = q
        mj.mj_kinematics(m, d)
        mj.mj_comPos(m, d)
        mj.mj_rne(m, d, 0, out)
        return out[self._dadr]

    def acceleration(self, q: np.ndarray, v: np.ndarray, u: np.ndarray) -> np.ndarray:
        """dv/dt of one state under input u: the system's actuation law as applied joint force, MuJoCo's dynamics."""
        torque = self.system.actuation_torque(v, u)
        if self._servo:
            torque = torque + self._gravity(q)
        self._qpos[self._qadr] = q
        self._qvel[self._dadr] = v
        self._qfrc[self._dadr] = torque
        self._forward(self.model, self.data)
        return self._qacc[self._dadr].copy()

    def rhs(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """dx/dt of one state, as system.rhs: for checks against the model."""
        n = self.system.nq
        return np.concatenate((x[n:], self.acceleration(x[:n], x[n:], u)))

    def _integrate(self, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Classical RK4 at h = tau / substeps with the input held."""
        n, h = self.system.nq, self.tau / self.substeps
        q, v = x0[:n].copy(), x0[n:].copy()
        acc = self.acceleration
        for _ in range(self.substeps):
            a1 = acc(q, v, u)
            q2, v2 = q + 0.5 * h * v, v + 0.5 * h * a1
            a2 = acc(q2, v2, u)
            q3, v3 = q + 0.5 * h * v2, v + 0.5 * h * a2
            a3 = acc(q3, v3, u)
            q4, v4 = q + h * v3, v + h * a3
            a4 = acc(q4, v4, u)
            q = q + h / 6.0 * (v + 2.0 * v2 + 2.0 * v3 + v4)
            v = v + h / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
        return np.concatenate((q, v))

    def step(self, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
        """One zero-hold period; raises PlantError on a bad input or a non-finite state."""
        x0 = np.asarray(x0, dtype=np.float64)
        u_t = np.asarray(u, dtype=np.float64)
        n = self.system.nq
        if x0.shape != (2 * n,) or u_t.shape != (n,):
            raise PlantError(
                f"plant got state shape {x0.shape} and input shape {u_t.shape}; expected ({2 * n},), ({n},)"
            )
        if not (np.all(np.isfinite(x0)) and np.all(np.isfinite(u_t))):
            raise PlantError(f"plant got a non-finite state or input: x0={x0.tolist()}, u={u_t.tolist()}")
        start = time.perf_counter()
        with np.errstate(over="ignore", invalid="ignore"):
            x1 = self._integrate(x0, u_t)
        self.step_times.append(time.perf_counter() - start)
        if not np.all(np.isfinite(x1)):
            raise PlantError(f"plant state became non-finite from x0={x0.tolist()}, u={u_t.tolist()}")
        return x1


def make_mujoco_plant(
    system: RigidArm,
    tau: float,
    robots: Mapping[str, Any] | None,
    robot: str | None,
    friction_scale: float = 1.0,
    mass_scale: float = 1.0,
    **settings: Any,
) -> MujocoPlant:
    """The MuJoCo plant of a robot named in the system's `robots` (None: the nominal model), with plant.yaml's
    friction and mass mismatch applied to the model system here."""
    if friction_scale != 1.0 or mass_scale != 1.0:
        if system.friction_scale != 1.0 or system.mass_scale != 1.0:
            raise ValueError(
                f"plant friction_scale={friction_scale}, mass_scale={mass_scale} on a system already scaled "
                f"({system.friction_scale}, {system.mass_scale}); expected the model system, scaled once"
            )
        system = system.with_mismatch(friction_scale=friction_scale, mass_scale=mass_scale)
    if robot is None:
        return MujocoPlant(system, tau, None, **settings)
    known = dict(robots or {})
    if robot not in known:
        raise ValueError(f"plant.robot={robot!r}; expected null or one of {sorted(known)} (system.robots)")
    try:
        return MujocoPlant(system, tau, known[robot], **settings)
    except ValueError as e:
        raise ValueError(f"system.robots.{robot}: {e}") from None
