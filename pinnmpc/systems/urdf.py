"""Serial rigid-body arms from a URDF: M(q) dv/dt + h(q, v) = joint torque, plus an actuation law from config.

The rigid-body algorithms come from libraries: adam (torch, batched and differentiable: the public rhs), adam's
CasADi backend compiled to C (training residuals, the classical NMPC) and Pinocchio (ABA in C++: the plant,
forward kinematics for drawings, golden checks). Only the actuation and friction law is written here, once,
over an array namespace, because URDF <dynamics> tags are not read by any of them.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np
import torch
from torch import Tensor

from pinnmpc.systems.actuation import settled_velocity
from pinnmpc.systems.actuation import xp as _xp
from pinnmpc.systems.base import Box, check_shapes
from pinnmpc.systems.urdf_casadi import CasadiArm
from pinnmpc.systems.urdf_files import URDF_DIR as URDF_DIR  # re-exported: where users' arms are looked up
from pinnmpc.systems.urdf_files import (
    Payload,
    _payload,
    locked_urdf,
    payload_urdf,
    resolve_urdf,
    revolute_joints,
    urdf_joint_limits,
)
from pinnmpc.systems.urdf_files import portable_urdf as portable_urdf  # re-exported: how an arm's file is recorded

ACTUATIONS = ("torque", "velocity_servo")
COMPENSATIONS = ("gravity", "bias")  # what a velocity servo adds to K (u - v): g(q), or g(q) + C(q, v) v


@dataclass(frozen=True)
class RigidArm(CasadiArm):
    """A fixed-base serial arm from a URDF with joint state x = (q, v) and one input per joint.

    actuation='torque': joint torque = u - D v - C tanh(s v) (viscous plus smoothed Coulomb friction).
    actuation='velocity_servo': joint torque = g(q) + K (u - v) - D v - C tanh(s v), a gravity-compensated velocity
    servo (D and C optional: none in the nominal arms, a fitted model's joint damping and friction the servo must
    overcome);
    servo_compensation='bias' adds the Coriolis and centrifugal torques too (g(q) + C(q, v) v, as franky-sim's joint
    velocity controller does), so that M(q) dv/dt = K (u - v) for the arm without a payload.
    mass_scale multiplies M and h (every link's mass and inertia) and friction_scale D and C, or K and C for a
    servo: plant mismatch for robustness runs; 1.0 is the nominal arm the surrogate learns.
    payload (a point mass on a link) and armature (per joint, on M's diagonal) are what an identified model adds;
    neither is scaled by mass_scale, and a servo compensates the gravity (and bias) of the arm without the payload.
    load is a point mass the servo knows (a Franka's configured end effector, such as its hand): part of the arm it
    compensates, so only its inertia shows in the motion.
    """

    name: str
    urdf: str
    tau: float
    state_box: Box
    input_box: Box
    actuation: str = "torque"
    joints: tuple[str, ...] = ()
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.80665)
    viscous: tuple[float, ...] = ()
    coulomb: tuple[float, ...] = ()
    coulomb_slope: float = 50.0
    servo_gain: tuple[float, ...] = ()
    friction_scale: float = 1.0
    mass_scale: float = 1.0
    state_units: tuple[str, ...] = ()
    input_units: tuple[str, ...] = ()
    tip_frame: str | None = None  # frame drawn as the tool tip (None: the last joint's child link)
    joint_limits: Box | None = None  # joint position limits, nq entries (None: none; see urdf_limits for the URDF's)
    payload: Payload | None = None  # a point mass fixed to a link ({mass, pos, link} in config); None: none
    armature: tuple[float, ...] = ()  # kg m^2 per joint added to M's diagonal (rotor inertia); (): none
    load: Payload | None = None  # a point mass the servo compensates with the arm ({mass, pos, link}); None: none
    servo_compensation: str = "gravity"  # a velocity servo's model-based torque: "gravity" g(q) or "bias" g + C v
    joint_prefix: str | None = None  # stripped from joint names in state and input names (None: "<name>_"); an
    #   identified model of an arm keeps its arm's names with it
    state_names: tuple[str, ...] = field(init=False)
    input_names: tuple[str, ...] = field(init=False)

    def __post_init__(self) -> None:
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", str(self.name)):
            raise ValueError(
                f"system name {self.name!r}; expected letters, digits and _ only, not starting with a digit (it names "
                "the compiled C functions)"
            )
        path = resolve_urdf(self.urdf)
        joints = tuple(self.joints) or tuple(revolute_joints(path))
        if not joints:
            raise ValueError(
                f"urdf={path}: no revolute joints; expected an arm of revolute joints (system.dynamics.joints)"
            )
        locked_urdf(path, joints)  # unknown joint names and what pinnmpc cannot model fail here, with the URDF's list
        n = len(joints)
        set_ = functools.partial(object.__setattr__, self)
        set_("joints", joints)
        set_("urdf", str(path))
        set_("gravity", tuple(float(g) for g in self.gravity))
        prefix = f"{self.name}_" if self.joint_prefix is None else self.joint_prefix
        short = [j.removeprefix(prefix) for j in joints]
        set_("state_names", (*(f"q_{j}" for j in short), *(f"v_{j}" for j in short)))
        set_("input_names", tuple(f"u_{j}" for j in short))
        set_("state_units", tuple(self.state_units) or ("rad",) * n + ("rad/s",) * n)
        if self.actuation not in ACTUATIONS:
            raise ValueError(f"{self.name}: actuation={self.actuation!r}; expected one of {list(ACTUATIONS)}")
        if self.servo_compensation not in COMPENSATIONS:
            raise ValueError(
                f"{self.name}: servo_compensation={self.servo_compensation!r}; expected one of {list(COMPENSATIONS)}"
            )
        default_unit = "N m" if self.actuation == "torque" else "rad/s"
        set_("input_units", tuple(self.input_units) or (default_unit,) * n)
        need = ("viscous", "coulomb") if self.actuation == "torque" else ("servo_gain",)
        for key in ("viscous", "coulomb", "servo_gain"):
            value = tuple(float(v) for v in getattr(self, key))
            set_(key, value)
            if (key in need or value) and (len(value) != n or any(not (math.isfinite(v) and v >= 0) for v in value)):
                raise ValueError(f"{self.name}: {key}={list(value)}; expected {n} finite numbers >= 0, one per joint")
        for key in ("tau", "coulomb_slope", "mass_scale", "friction_scale"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or v < 0:
                raise ValueError(f"{self.name}: {key}={v!r}; expected a finite number >= 0")
        if not self.tau > 0 or not self.mass_scale > 0:
            raise ValueError(f"{self.name}: need tau > 0 and mass_scale > 0, got {self.tau} and {self.mass_scale}")
        set_("payload", _payload(self.name, self.payload))
        set_("load", _payload(self.name, self.load, "load"))
        for mass in (self.payload, self.load):
            if mass is not None:
                payload_urdf(locked_urdf(path, joints), mass, self.tip_frame, joints)  # a bad link fails here
        armature = tuple(self.armature or ())
        if armature and (len(armature) != n or any(not (math.isfinite(float(v)) and v >= 0) for v in armature)):
            raise ValueError(f"{self.name}: armature={list(armature)}; expected {n} finite numbers >= 0 (kg m^2)")
        set_("armature", tuple(float(v) for v in armature))
        if self.joint_limits is not None and self.joint_limits.dim != n:
            raise ValueError(f"{self.name}: joint_limits has {self.joint_limits.dim} entries; expected {n} (joints)")
        if self.state_box.dim != 2 * n or self.input_box.dim != n:
            raise ValueError(
                f"{self.name}: state_box has {self.state_box.dim} and input_box {self.input_box.dim} entries; "
                f"expected {2 * n} and {n} for joints {list(joints)}"
            )
        self._check_pinocchio()

    def _check_pinocchio(self) -> None:
        """At load, not mid-run: the tip frame exists and every joint moves some inertia (else M(q) is singular and
        the plant's ABA returns NaN)."""
        import pinocchio as pin

        model, data = self.pinocchio
        if self.tip_frame and not model.existFrame(self.tip_frame):
            frames = [f.name for f in model.frames]
            raise ValueError(
                f"{self.name}: tip_frame={self.tip_frame!r} is not a frame of {self.urdf}; expected one of {frames}"
            )
        order = self._pin_order if self._pin_order is not None else np.arange(self.nq)
        low, high = np.array(self.state_box.low[: self.nq]), np.array(self.state_box.high[: self.nq])
        for q in (np.zeros(self.nq), low, high, (low + high) / 2):
            m = pin.crba(model, data, np.ascontiguousarray(q[order]))
            m = np.triu(m) + np.triu(m, 1).T
            if np.linalg.eigvalsh(m).min() <= 1e-12 * max(1.0, float(np.abs(m).max())):
                weak = [self.joints[order[i]] for i in range(self.nq) if m[i, i] <= 1e-12 * max(1.0, float(m.max()))]
                raise ValueError(
                    f"urdf={self.urdf}: the mass matrix is singular at q={q.round(3).tolist()} (joints {weak or '?'} "
                    "move no mass or inertia); expected every link beyond a listed joint to carry <inertial> mass"
                )

    @functools.cached_property
    def _pin_order(self) -> np.ndarray | None:
        """Pinocchio's joint order (tree order) as indices into self.joints; None when they agree."""
        model, _ = self.pinocchio
        names = list(model.names)[1:]
        order = np.array([self.joints.index(n) for n in names])
        return None if np.array_equal(order, np.arange(self.nq)) else order

    @property
    def nq(self) -> int:
        """Number of joints (positions come first in the state)."""
        return len(self.joints)

    @property
    def urdf_limits(self) -> Box:
        """The URDF's own position limits of the joints (what `joint_limits` of a URDF arm should repeat)."""
        return urdf_joint_limits(Path(self.urdf), self.joints)

    def with_mismatch(self, friction_scale: float = 1.0, mass_scale: float = 1.0) -> RigidArm:
        """The same arm with scaled friction (or servo gain) and inertia: a plant the controller does not know."""
        return dataclasses.replace(self, friction_scale=friction_scale, mass_scale=mass_scale)

    # -- the one hand-written law ---------------------------------------------------------------------------
    def actuation_torque(self, v: Any, u: Any) -> Any:
        """Joint torque from the input, apart from gravity compensation (any array namespace)."""
        f = self.friction_scale
        if self.actuation == "torque":
            return u - f * (self._coeffs("viscous", v) * v + self._coeffs("coulomb", v) * self._slip(v))
        out = f * self._coeffs("servo_gain", v) * (u - v)
        if self.viscous:  # the joint's own damping, which the servo must overcome too (a fitted model's)
            out = out - f * self._coeffs("viscous", v) * v
        return out - self.dry_friction(v) if self.coulomb else out

    def dry_friction(self, v: Any) -> Any:
        """The joints' dry friction torque at velocity v, as the actuation law applies it (any array namespace; zero
        for an arm without `coulomb`): what a frozen-arm prior with moving friction integrates."""
        return self.friction_scale * self._coeffs("coulomb", v) * self._slip(v) if self.coulomb else 0 * v

    def _slip(self, v: Any) -> Any:
        """tanh(slope v): the dry friction's direction, smoothed."""
        return _xp(v).tanh(self.coulomb_slope * v)

    def _coeffs(self, key: str, like: Any) -> Any:
        """Per-joint coefficients in like's array type."""
        if isinstance(like, np.ndarray):
            return self._numpy_coeffs[key]
        value = getattr(self, key)
        if isinstance(like, Tensor):
            return torch.tensor(value, dtype=like.dtype, device=like.device)
        return ca.DM(value)

    @functools.cached_property
    def _numpy_coeffs(self) -> dict[str, np.ndarray]:
        """Coefficient arrays built once: the plant calls the law thousands of times per step."""
        return {k: np.asarray(getattr(self, k), dtype=np.float64) for k in ("viscous", "coulomb", "servo_gain")}

    def _bias(self, h: Any, g: Any) -> Any:
        """What M dv/dt must balance besides the actuation: h, less gravity where the servo compensates it."""
        return self.mass_scale * (h - g) if self.actuation == "velocity_servo" else self.mass_scale * h

    # -- torch (adam): the public, differentiable rhs ---------------------------------------------------------
    @functools.cached_property
    def servo_urdf(self) -> str:
        """The URDF text of the arm a servo compensates: the locked arm, plus the load's link when there is one."""
        text = locked_urdf(Path(self.urdf), self.joints)
        if self.load is None:
            return text
        return payload_urdf(text, self.load, self.tip_frame, self.joints, self.mass_scale, "pinnmpc_load")

    @functools.cached_property
    def model_urdf(self) -> str:
        """The URDF text every backend loads: the servo's arm, plus the payload's link when there is one."""
        if self.payload is None:
            return self.servo_urdf
        return payload_urdf(self.servo_urdf, self.payload, self.tip_frame, self.joints, self.mass_scale)

    @functools.cached_property
    def _adam(self) -> dict[tuple[torch.dtype, bool], Any]:
        """adam KinDynComputations per dtype (gravity passed in that dtype: adam's default is float32)."""
        return {}

    def _kindyn(self, dtype: torch.dtype, nominal: bool = False) -> Any:
        """adam's torch model in this dtype (nominal: the servo's arm, without the payload), built on first use."""
        if (dtype, nominal) not in self._adam:
            from adam.pytorch import KinDynComputations

            text = self.servo_urdf if nominal else self.model_urdf
            with torch.inference_mode(False):  # cached constants must stay usable by later autograd calls
                g = torch.tensor([*self.gravity, 0.0, 0.0, 0.0], dtype=dtype)
                kd = KinDynComputations(text, list(self.joints), dtype=dtype, gravity=g, device="cpu")
                self._adam[dtype, nominal] = kd
        return self._adam[dtype, nominal]

    def dynamics_terms(self, q: Tensor, v: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """M (B, n, n), h (B, n) and what a servo compensates (B, n): the gravity, or the bias h of servo_compensation
        'bias', of the arm without the payload, for a flat batch, the joint block of adam's floating base."""
        kd, b, n = self._kindyn(q.dtype), q.shape[0], self.nq
        base, still = torch.eye(4, dtype=q.dtype).expand(b, 4, 4), torch.zeros(b, 6, dtype=q.dtype)
        m = kd.mass_matrix(base, q).reshape(b, n + 6, n + 6)[:, 6:, 6:]
        h = kd.bias_force(base, q, still, v).reshape(b, n + 6)[:, 6:]
        servo = self.actuation == "velocity_servo"
        kg = self._kindyn(q.dtype, nominal=True) if servo and self.payload is not None else kd
        if not servo:
            g = 0 * h
        elif self.servo_compensation == "bias":
            g = h if kg is kd else kg.bias_force(base, q, still, v).reshape(b, n + 6)[:, 6:]
        else:
            g = kg.gravity_term(base, q).reshape(b, n + 6)[:, 6:]
        if self.armature:
            return self.mass_scale * m + torch.diag(torch.tensor(self.armature, dtype=q.dtype)), h, g
        return self.mass_scale * m, h, g

    def coriolis_torque(self, q: Tensor, v: Tensor) -> Tensor:
        """C(q, v) v (B, n) through adam, scaled as the arm's h, less what a servo compensates: what a frozen-arm
        prior with moving terms holds."""
        kd, b, n = self._kindyn(q.dtype), q.shape[0], self.nq
        base, still = torch.eye(4, dtype=q.dtype).expand(b, 4, 4), torch.zeros(b, 6, dtype=q.dtype)
        c = kd.coriolis_term(base, q, still, v).reshape(b, n + 6)[:, 6:]
        if self.compensates_bias:
            c = c - self._kindyn(q.dtype, nominal=True).coriolis_term(base, q, still, v).reshape(b, n + 6)[:, 6:]
        return self.mass_scale * c

    @property
    def compensates_bias(self) -> bool:
        """Whether the actuation holds the Coriolis torques of the arm without the payload (servo_compensation)."""
        return self.actuation == "velocity_servo" and self.servo_compensation == "bias"

    # -- the arm frozen at q0: the linear part a learned flow map builds on (pinnmpc.surrogate.prior) -----------------
    @property
    def linear_gain(self) -> tuple[float, ...]:
        """kv of the frozen model: the actuation's torque per unit joint velocity (D, or K + D of a servo), scaled."""
        if self.actuation == "torque":
            return tuple(self.friction_scale * d for d in self.viscous)
        damping = self.viscous or (0.0,) * len(self.servo_gain)
        return tuple(self.friction_scale * (k + d) for k, d in zip(self.servo_gain, damping))

    def frozen_terms(self, q: Tensor, u: Tensor, settled: bool = True) -> tuple[Tensor, Tensor]:
        """M(q) (B, n, n) and c0 (B, n) of M(q) dv/dt = c0 - kv v: the arm held at q, without Coriolis terms (a
        servo's dry friction taken where it settles; settled=False: without it); its exact solution over a period
        carries most of the flow (the rest is learned)."""
        m, g, comp = self.dynamics_terms(q, torch.zeros_like(q))  # h at v = 0 is gravity
        return m, self._frozen_drive(g, u, comp, settled)

    def _frozen_drive(self, g: Any, u: Any, comp: Any = None, settled: bool = True) -> Any:
        """c0: the actuation at rest less the gravity it must hold (for a servo: only a payload's, which its
        compensation of the arm without it leaves). A servo's dry friction enters as the torque it holds at the
        velocity the frozen servo settles at (so that steady state is exact, stick included) unless settled=False; a
        torque-driven arm's stays out, and an arm without dry friction (every nominal servo) gets exactly the term
        without it."""
        if self.actuation == "torque":
            return u - self.mass_scale * g
        gain = self.friction_scale * self._coeffs("servo_gain", u)
        drive = gain * u - self._bias(g, comp) if self.payload is not None else gain * u
        if not self.coulomb or not settled:
            return drive
        per_speed = self._coeffs("servo_gain", u)  # torque per unit velocity: K, and the joint's damping D with it
        if self.viscous:
            per_speed = per_speed + self._coeffs("viscous", u)
        linear = self.friction_scale * per_speed
        ratio = self._coeffs("coulomb", u) / per_speed  # the velocity the friction takes off
        return linear * settled_velocity(drive / linear, ratio, self.coulomb_slope)

    def _rhs_torch(self, x: Tensor, u: Tensor) -> Tensor:
        """dx/dt through adam: differentiable to any order."""
        lead, n = x.shape[:-1], self.nq
        x, u = x.reshape(-1, 2 * n), u.reshape(-1, n)
        q, v = x[:, :n], x[:, n:]
        m, h, g = self.dynamics_terms(q, v)
        # M is symmetric positive definite: Cholesky, which (unlike torch.linalg.solve in torch 2.13) also
        # differentiates right under vmap(jacfwd)
        rhs = (self.actuation_torque(v, u) - self._bias(h, g)).unsqueeze(-1)
        acc = torch.cholesky_solve(rhs, torch.linalg.cholesky(m)).squeeze(-1)
        return torch.cat((v, acc), dim=-1).reshape(*lead, 2 * n)

    # -- numpy (Pinocchio): the plant -------------------------------------------------------------------------
    @functools.cached_property
    def pinocchio(self) -> tuple[Any, Any]:
        """Pinocchio model and data of the arm with the other joints locked."""
        import pinocchio as pin

        model = pin.buildModelFromXML(self.model_urdf)
        model.gravity.linear = np.array(self.gravity)
        if self.armature:  # in Pinocchio's joint order; over mass_scale, as aba is given torque / mass_scale
            order = [self.joints.index(name) for name in list(model.names)[1:]]
            model.armature = np.asarray(self.armature)[order] / self.mass_scale
        return model, model.createData()

    @functools.cached_property
    def _nominal_pinocchio(self) -> tuple[Any, Any]:
        """The servo's arm (load included) without payload and armature: the gravity a servo compensates, the tip
        drawn."""
        if self.payload is None and not self.armature:
            return self.pinocchio
        import pinocchio as pin

        model = pin.buildModelFromXML(self.servo_urdf)
        model.gravity.linear = np.array(self.gravity)
        return model, model.createData()

    def _rhs_state(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """dx/dt of one state by Pinocchio's ABA: the plant's call, thousands of times per step."""
        import pinocchio as pin

        model, data = self.pinocchio
        q, v = x[: self.nq], x[self.nq :]
        torque = self.actuation_torque(v, u)
        order = self._pin_order
        if order is not None:  # joints listed in another order than the tree's: Pinocchio's order and back
            q, vp, torque = q[order], v[order], torque[order]
        else:
            vp = v
        if self.actuation == "velocity_servo":
            nominal, nominal_data = self._nominal_pinocchio
            held = (
                pin.nonLinearEffects(nominal, nominal_data, q, vp)
                if self.servo_compensation == "bias"
                else pin.computeGeneralizedGravity(nominal, nominal_data, q)
            )
            torque = torque + self.mass_scale * held
        acc = pin.aba(model, data, q, vp, torque / self.mass_scale)
        if order is not None:
            acc = acc[np.argsort(order)]
        return np.concatenate((v, acc))

    def _rhs_numpy(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """dx/dt for numpy arrays: ABA runs per state in C++, so a batch is a loop over states."""
        if x.ndim == 1 and u.ndim == 1:
            return self._rhs_state(x, u)
        n = self.nq
        lead = np.broadcast_shapes(x.shape[:-1], u.shape[:-1])
        xs = np.broadcast_to(x, (*lead, 2 * n)).reshape(-1, 2 * n)
        us = np.broadcast_to(u, (*lead, n)).reshape(-1, n)
        return np.stack([self._rhs_state(xi, ui) for xi, ui in zip(xs, us)]).reshape(*lead, 2 * n)

    def rhs(self, x: Tensor | np.ndarray, u: Tensor | np.ndarray) -> Tensor | np.ndarray:
        """Batched dx/dt: torch (adam, differentiable) for tensors, Pinocchio ABA for numpy arrays."""
        if isinstance(x, Tensor):
            check_shapes(self, x, u)
            return self._rhs_torch(x, torch.as_tensor(u, dtype=x.dtype))
        x, u = np.asarray(x, dtype=np.float64), np.asarray(u, dtype=np.float64)
        if x.shape[-1] != 2 * self.nq or u.shape[-1] != self.nq:
            check_shapes(self, x, u)
        return self._rhs_numpy(x, u)

    @functools.cached_property
    def compiled(self) -> Any:
        """The CasADi rhs and its VJP compiled to C (built on first use, cached on disk)."""
        from pinnmpc.systems.compiled import CompiledRhs

        tag = f"{self.name}_f{self.friction_scale:g}_m{self.mass_scale:g}".replace(".", "p")
        return CompiledRhs(tag, self.casadi_rhs())

    def fast_rhs(self, x: Tensor, u: Tensor) -> Tensor:
        """dx/dt for training: the compiled rhs, first-order differentiable (backward through its VJP)."""
        from pinnmpc.systems.compiled import CasadiRhs

        lead = x.shape[:-1]
        y = CasadiRhs.apply(x.reshape(-1, 2 * self.nq), u.reshape(-1, self.nq), self.compiled)
        return y.reshape(*lead, 2 * self.nq)

    def residual(self, x: Tensor, dxdt: Tensor, u: Tensor, form: str = "explicit") -> Tensor:
        """ODE residual dxdt - f(x, u) through the compiled rhs ('explicit'; the only form for URDF arms)."""
        if form != "explicit":
            raise ValueError(f"{self.name}: residual_form={form!r}; URDF arms support 'explicit' only")
        return dxdt - self.fast_rhs(x, u)

    # -- drawing ---------------------------------------------------------------------------------------------
    def kinematics(self, q: np.ndarray) -> np.ndarray:
        """Joint origins and the tip, (N, n + 1, 3) in the base frame, for stick drawings."""
        from pinnmpc.systems.urdf_drawing import stick_points

        return stick_points(self, q)
