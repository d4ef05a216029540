"""A robot that is not the model: MuJoCo compiles the arm's URDF, optionally with effects the model lacks.

The controller and the surrogate know the URDF's rigid bodies and the system's actuation law. This plant simulates
them in another engine (MuJoCo instead of Pinocchio/adam), and a named robot (conf/system/<arm>.yaml, `robots`) adds
what the nominal model leaves out (pinnmpc/plant/effects.py: a payload, armature, dry friction, and effects outside the
identification's class: Stribeck and load-dependent friction, torque-speed droop, cogging, actuator lag). Each
period holds the input and integrates by explicit RK4 at a fixed step around `mujoco.mj_forward`, applying the
system's actuation law and the robot's applied effects at every stage; the velocity servo compensates the gravity
of the nominal arm it was tuned on, so a payload's weight is a real mismatch.
"""

from __future__ import annotations

import dataclasses
import time
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pinnmpc.plant.effects import NOMINAL, EffectLaw, RobotEffects, attribute_effects, robot_effects
from pinnmpc.plant.scipy_plant import PlantError
from pinnmpc.plant.settings import MujocoPlantSettings
from pinnmpc.systems import RigidArm
from pinnmpc.systems.urdf import locked_urdf

PAYLOAD_BODY = "pinnmpc_payload"  # the point mass's body in the compiled model


def _import_mujoco() -> Any:
    """MuJoCo on first use, so the package imports without it; its absence is said in one line."""
    try:
        import mujoco
    except ImportError:
        raise ModuleNotFoundError("plant=mujoco needs the mujoco package: pip install mujoco") from None
    return mujoco


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


def compile_arm(system: RigidArm, effects: RobotEffects = NOMINAL) -> Any:
    """The arm as a mujoco.MjModel: URDF inertias as written (scaled by system.mass_scale), gravity from the system,
    no contacts, limits, damping or springs; the robot's payload and joint attributes (armature, frictionloss) on
    top (its applied effects are MujocoPlant's)."""
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
    for f in attribute_effects():
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
    robot: Mapping[str, Any] | None = None  # None: the nominal model; else a robot description (plant/effects.py)
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
        if self._servo:  # the servo's gravity (or bias) compensation: the nominal arm's, computed in its own data
            self._servo_model = compile_arm(self.system) if self.robot is not None else self.model
            self._servo_data = mujoco.MjData(self._servo_model)  # qvel 0 (gravity alone) unless it compensates bias
            self._gravity_out = np.empty(n)
            self._with_bias = self.system.compensates_bias
        d = self.data  # views into MjData, bound once: the stage function runs 4 substeps times per period
        self._qpos, self._qvel, self._qfrc, self._qacc = d.qpos, d.qvel, d.qfrc_applied, d.qacc
        self._forward = mujoco.mj_forward
        self._mujoco = mujoco
        self._law = EffectLaw(self.effects) if self.effects.applied else None
        self._lag = self.effects.lag
        self._held: tuple[np.ndarray, np.ndarray] | None = None  # lag: (the last period's end state, filter state)

    def _gravity(self, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        """g(q), or g(q) + C(q, v) v (system.servo_compensation 'bias'), of the nominal arm (mass-scaled as the
        system): what its velocity servo compensates."""
        mj, m, d, out = self._mujoco, self._servo_model, self._servo_data, self._gravity_out
        d.qpos[self._qadr] = q
        mj.mj_kinematics(m, d)
        mj.mj_comPos(m, d)
        if self._with_bias:
            d.qvel[self._dadr] = v
            mj.mj_comVel(m, d)
        mj.mj_rne(m, d, 0, out)
        return out[self._dadr]

    def acceleration(self, q: np.ndarray, v: np.ndarray, u: np.ndarray) -> np.ndarray:
        """dv/dt of one state under input u (the actuator's, after any lag): the system's actuation law and the
        robot's applied effects as joint force, MuJoCo's dynamics."""
        torque = self.system.actuation_torque(v, u)
        if self._servo:
            torque = torque + self._gravity(q, v)
        if self._law is not None:  # what the motor gives, through the robot's droop, friction and cogging
            torque = self._law.joint_force(q, v, torque)
        self._qpos[self._qadr] = q
        self._qvel[self._dadr] = v
        self._qfrc[self._dadr] = torque
        self._forward(self.model, self.data)
        return self._qacc[self._dadr].copy()

    def needed_input(self, q: np.ndarray, v: np.ndarray, a: np.ndarray) -> np.ndarray:
        """The actuator's input that gives acceleration a at (q, v) on this robot (before any lag): MuJoCo's inverse
        dynamics of the arm (its dry friction as Coulomb, tanh(slip_slope v)) back through the applied effects and
        the actuation law, which is affine in the input. For sizing a robot against the input box."""
        mj = self._mujoco
        if not hasattr(self, "_inverse"):  # the robot without its friction constraint, which mj_inverse cannot see
            smooth = dataclasses.replace(self.effects, frictionloss=(0.0,) * self.system.nq)
            self._inverse = compile_arm(self.system, smooth)
            self._inverse_data = mj.MjData(self._inverse)
        m, d = self._inverse, self._inverse_data
        d.qpos[self._qadr], d.qvel[self._dadr], d.qacc[self._dadr] = q, v, a
        mj.mj_inverse(m, d)
        dry = np.asarray(self.effects.frictionloss or (0.0,) * self.system.nq)
        joint = d.qfrc_inverse[self._dadr] + dry * np.tanh(self.effects.slip_slope * v)
        motor = joint if self._law is None else self._law.needed_motor(q, v, joint)
        if self._servo:
            motor = motor - self._gravity(q, v)
        zero, one = self.system.actuation_torque(v, 0.0 * v), self.system.actuation_torque(v, 1.0 + 0.0 * v)
        return (motor - zero) / (one - zero)

    def rhs(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """dx/dt of one state, as system.rhs: for checks against the model."""
        n = self.system.nq
        return np.concatenate((x[n:], self.acceleration(x[:n], x[n:], u)))

    def _integrate(self, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Classical RK4 at h = tau / substeps with the input held (through the actuator's lag where it has one)."""
        if self._lag:
            return self._integrate_lagged(x0, u)
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

    def _integrate_lagged(self, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
        """RK4 of (q, v, a) with the actuator's input a filtered, da/dt = (u - a) / lag. The filter state carries over
        when x0 is the last period's end state (a closed loop), else it starts settled at u (a lone step)."""
        n, h, k = self.system.nq, self.tau / self.substeps, 1.0 / self._lag
        held = self._held
        a = held[1].copy() if held is not None and np.array_equal(held[0], x0) else u.copy()
        q, v = x0[:n].copy(), x0[n:].copy()
        acc = self.acceleration
        for _ in range(self.substeps):
            b1 = k * (u - a)
            a1 = acc(q, v, a)
            q2, v2, c2 = q + 0.5 * h * v, v + 0.5 * h * a1, a + 0.5 * h * b1
            b2, a2 = k * (u - c2), acc(q2, v2, c2)
            q3, v3, c3 = q + 0.5 * h * v2, v + 0.5 * h * a2, a + 0.5 * h * b2
            b3, a3 = k * (u - c3), acc(q3, v3, c3)
            q4, v4, c4 = q + h * v3, v + h * a3, a + h * b3
            b4, a4 = k * (u - c4), acc(q4, v4, c4)
            q = q + h / 6.0 * (v + 2.0 * v2 + 2.0 * v3 + v4)
            v = v + h / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
            a = a + h / 6.0 * (b1 + 2.0 * b2 + 2.0 * b3 + b4)
        x1 = np.concatenate((q, v))
        self._held = (x1.copy(), a)
        return x1

    def period_from(self, x0: np.ndarray, u: np.ndarray, actuator: np.ndarray) -> np.ndarray:
        """x(tau) from x0 under u with the actuator's filter starting at `actuator` (the input it still carries;
        ignored without a lag), this robot's own prediction, apart from any closed loop's state: what a model could
        at best predict (examples/shop_model_floor.py)."""
        x0, loop = np.array(x0, dtype=np.float64), self._held
        self._held = (x0.copy(), np.array(actuator, dtype=np.float64)) if self._lag else None
        try:
            return self._integrate(x0, np.array(u, dtype=np.float64))
        finally:
            self._held = loop  # the closed loop's filter state, as it was

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


def input_demand(plant: MujocoPlant, t: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Per sample of a reference (t, x), the largest fraction of the input box a joint's command needs on the
    plant's robot (inverse dynamics, accelerations by finite differences; with an actuator lag T the command
    u + T du/dt that the lag turns into u): above 1, the robot cannot follow it."""
    n = plant.system.nq
    acc = np.gradient(x[:, n:], t, axis=0)
    u = np.stack([plant.needed_input(x[i, :n], x[i, n:], acc[i]) for i in range(len(t))])
    if plant.effects.lag:
        u = u + plant.effects.lag * np.gradient(u, t, axis=0)
    low, high = np.asarray(plant.system.input_box.low), np.asarray(plant.system.input_box.high)
    fraction = np.where(u >= 0, u / np.where(high > 0, high, np.inf), u / np.where(low < 0, low, -np.inf))
    return np.abs(fraction).max(axis=1)


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
