"""Schunk PowerCube two-link arm (Fehr et al. 2020): the single source of truth for its physics.

The coefficients are the identified model collected into closed form (see
../shared/powercube/MODEL.md). They are facts of the model, not tuning knobs;
what a user may change (training box, input bounds, plant mismatch) lives in
conf/system/powercube.yaml.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any

import casadi as ca
import numpy as np
import torch
from torch import Tensor

from pinnmpc.systems.base import Box, check_shapes

GRAVITY = 9.80665  # scipy.constants.g, m/s^2


@dataclass(frozen=True)
class PowerCubeParams:
    """Identified coefficients; the two scales model plant mismatch (1.0 = nominal)."""

    c: float = 0.3107549862  # coupling inertia term, kg m^2
    m11: float = 2.3212965868565  # constant part of M11
    m12: float = 0.6693697768565  # constant part of M12 = M21
    m22: float = 2.0261489768565  # M22
    grav_a: float = 1.626138  # gravity moment of link A (times g)
    grav_ab: float = 1.72641659  # gravity moment of link B (times g)
    visc_a: float = 76.556  # viscous friction joint A
    tanh_a: tuple[tuple[float, float], ...] = ((3.924, 5.0), (10.838, 10.0), (2.236, 20.0))  # (gain, slope)
    visc_b: float = 56.231  # viscous friction joint B
    tanh_b: tuple[tuple[float, float], ...] = ((0.368, 5.0), (0.368, 10.0), (8.342, 100.0))  # (gain, slope)
    coulomb_b: float = 0.492  # Coulomb friction joint B (sign term)
    gain: float = 161.0  # input matrix B = gain * I (current to torque)
    friction_scale: float = 1.0  # multiplies every friction term (plant mismatch studies)
    mass_scale: float = 1.0  # multiplies every link's mass and inertia: M, Coriolis and gravity (plant mismatch)

    def __post_init__(self) -> None:
        for name in ("friction_scale", "mass_scale"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
                raise ValueError(f"PowerCube {name} must be a finite number, got {value!r}")
        if self.mass_scale <= 0 or self.friction_scale < 0:
            raise ValueError(
                f"need mass_scale > 0 and friction_scale >= 0, got {self.mass_scale} and {self.friction_scale}"
            )


DEFAULT_PARAMS = PowerCubeParams()


Array = Tensor | np.ndarray


CASADI = SimpleNamespace(  # the functions the formulas use, for CasADi symbols (the classical NMPC)
    sin=ca.sin, cos=ca.cos, tanh=ca.tanh, sign=ca.sign, stack=lambda xs, _axis: ca.vertcat(*xs)
)


def _xp(a: Any) -> Any:
    """Array namespace of a: the same formulas serve torch (PINN, controller), numpy (scipy plant) and CasADi."""
    if isinstance(a, Tensor):
        return torch
    if isinstance(a, ca.SX | ca.MX | ca.DM):
        return CASADI
    return np


def _at(a: Any, i: int) -> Any:
    """Coordinate i along the last axis (a CasADi column vector has no leading batch axes)."""
    return a[i] if isinstance(a, ca.SX | ca.MX | ca.DM) else a[..., i]


def _friction(v: Array, viscous: float, tanh_terms: tuple[tuple[float, float], ...]) -> Array:
    """Viscous plus smoothed-Coulomb friction torque (positive opposes motion)."""
    xp = _xp(v)
    out = viscous * v
    for gain, slope in tanh_terms:
        out = out + gain * xp.tanh(slope * v)
    return out


def mass_matrix(x: Array, p: PowerCubeParams = DEFAULT_PARAMS) -> tuple[Array, Array, Array]:
    """Entries (M11, M12, M22) of the symmetric mass matrix M(beta)."""
    cb = _xp(x).cos(_at(x, 1))
    s = p.mass_scale
    return s * (p.m11 + 2 * p.c * cb), s * (p.m12 + p.c * cb), s * p.m22 + 0 * cb


def generalized_forces(
    x: Array, u: Array, p: PowerCubeParams = DEFAULT_PARAMS, coulomb_sign: Array | None = None
) -> tuple[Array, Array]:
    """Right side h - k + B u of M qdd = h - k + B u; coulomb_sign replaces sign(dbeta) (the plant's stick-slip)."""
    xp = _xp(x)
    alpha, beta, da, db = _at(x, 0), _at(x, 1), _at(x, 2), _at(x, 3)
    sb = xp.sin(beta)
    s = p.mass_scale
    k1 = -s * p.c * sb * (2 * da * db + db * db)
    k2 = s * p.c * sb * da * da
    g_ab = s * p.grav_ab * GRAVITY * xp.sin(alpha + beta)  # gravity moments are mass times lever: scaled too
    f = p.friction_scale
    h1 = s * p.grav_a * GRAVITY * xp.sin(alpha) + g_ab - f * _friction(da, p.visc_a, p.tanh_a)
    sign_b = xp.sign(db) if coulomb_sign is None else coulomb_sign
    h2 = g_ab - f * (_friction(db, p.visc_b, p.tanh_b) + p.coulomb_b * sign_b)
    return h1 - k1 + p.gain * _at(u, 0), h2 - k2 + p.gain * _at(u, 1)


def rhs(x: Array, u: Array, p: PowerCubeParams = DEFAULT_PARAMS, coulomb_sign: Array | None = None) -> Array:
    """dx/dt = [dalpha, dbeta, M^-1 (h - k + B u)], with the 2x2 solve in closed form."""
    m11, m12, m22 = mass_matrix(x, p)
    r1, r2 = generalized_forces(x, u, p, coulomb_sign)
    det = m11 * m22 - m12 * m12
    dda = (m22 * r1 - m12 * r2) / det
    ddb = (m11 * r2 - m12 * r1) / det
    return _xp(x).stack((_at(x, 2), _at(x, 3), dda, ddb), -1)


def mass_residual(x: Array, dxdt: Array, u: Array, p: PowerCubeParams = DEFAULT_PARAMS) -> Array:
    """The paper's residual [dq/dt - qd ; M d(qd)/dt + k - h - B u]: no division by det M."""
    m11, m12, m22 = mass_matrix(x, p)
    r1, r2 = generalized_forces(x, u, p)
    acc_a, acc_b = dxdt[..., 2], dxdt[..., 3]
    return _xp(x).stack(
        (
            dxdt[..., 0] - x[..., 2],
            dxdt[..., 1] - x[..., 3],
            m11 * acc_a + m12 * acc_b - r1,
            m12 * acc_a + m22 * acc_b - r2,
        ),
        -1,
    )


@dataclass(frozen=True)
class PowerCube:
    """The PowerCube as a System: physics plus the box a surrogate is trained on."""

    params: PowerCubeParams = field(default_factory=PowerCubeParams)
    state_box: Box = Box((-math.pi, -math.pi, -2.5, -2.5), (math.pi, math.pi, 2.5, 2.5))
    input_box: Box = Box((-0.5, -0.5), (0.5, 0.5))
    joint_limits: Box | None = None  # none: both joints turn all the way round
    tau: float = 0.2  # control period of the paper, s
    link_lengths: tuple[float, float] = (0.5, 0.4)  # m, for drawings only (not part of the identified model)
    name: str = "powercube"
    state_names: tuple[str, ...] = ("alpha", "beta", "dalpha", "dbeta")
    input_names: tuple[str, ...] = ("u1", "u2")
    state_units: tuple[str, ...] = ("rad", "rad", "rad/s", "rad/s")
    input_units: tuple[str, ...] = ("A", "A")
    nq: int = 2  # joints; positions come first in the state
    coulomb_joints: tuple[int, ...] = (1,)  # joints whose friction has a sign(v) term (the plant locates its switches)

    def with_mismatch(self, friction_scale: float = 1.0, mass_scale: float = 1.0) -> PowerCube:
        """The same arm with scaled friction and mass matrix: a plant the controller does not know."""
        params = dataclasses.replace(self.params, friction_scale=friction_scale, mass_scale=mass_scale)
        return dataclasses.replace(self, params=params)

    def casadi_rhs(self, coulomb_width: float | None = None) -> ca.Function:
        """dx/dt = f(x, u) as a CasADi SX function: the same closed form, evaluated on symbols; with coulomb_width
        sign(dbeta) becomes tanh(dbeta / width), a smooth model for an OCP the exact one leaves without a solution."""
        x, u = ca.SX.sym("x", 4), ca.SX.sym("u", 2)
        if coulomb_width is not None and not coulomb_width > 0:
            raise ValueError(f"coulomb_width must be > 0 (rad/s) or null, got {coulomb_width}")
        sign_b = None if coulomb_width is None else ca.tanh(x[3] / coulomb_width)
        return ca.Function("powercube_rhs", [x, u], [rhs(x, u, self.params, coulomb_sign=sign_b)], {"cse": True})

    def casadi_inverse_dynamics(self, coulomb_width: float | None = None) -> ca.Function:
        """r(q, v, a, u) = M(q) a - f(q, v, u) of the closed form (SX), smoothed as casadi_rhs with coulomb_width:
        the collocation's residual without M^-1, as every arm gives it."""
        q, v, a, u = (ca.SX.sym(name, n) for name, n in (("q", 2), ("v", 2), ("a", 2), ("u", 2)))
        x = ca.vertcat(q, v)
        sign = None if coulomb_width is None else ca.tanh(v[self.coulomb_joints[0]] / coulomb_width)
        m11, m12, m22 = mass_matrix(x, self.params)
        f1, f2 = generalized_forces(x, u, self.params, coulomb_sign=sign)
        r = ca.vertcat(m11 * a[0] + m12 * a[1] - f1, m12 * a[0] + m22 * a[1] - f2)
        return ca.Function(
            f"{self.name}_inverse_dynamics", [q, v, a, u], [r], ["q", "v", "a", "u"], ["r"], {"cse": True}
        )

    def kinematics(self, q: np.ndarray) -> np.ndarray:
        """Base, elbow and tip (N, 3, 3) in the vertical plane, alpha from hanging down, beta relative to link 1."""
        q = np.atleast_2d(np.asarray(q, dtype=np.float64))
        (l1, l2), a, ab = self.link_lengths, q[:, 0], q[:, 0] + q[:, 1]
        zero = np.zeros_like(a)
        elbow = np.stack([l1 * np.sin(a), -l1 * np.cos(a), zero], axis=-1)
        tip = elbow + np.stack([l2 * np.sin(ab), -l2 * np.cos(ab), zero], axis=-1)
        return np.stack([np.zeros_like(elbow), elbow, tip], axis=1)

    def rhs(self, x: Array, u: Array) -> Array:
        """Batched dx/dt: differentiable for torch tensors, fast for numpy arrays (the plant)."""
        check_shapes(self, x, u)
        return rhs(x, u, self.params)

    def rhs_coulomb(self, x: np.ndarray, u: np.ndarray, signs: np.ndarray) -> np.ndarray:
        """dx/dt with sign(v) of each coulomb_joints entry replaced by signs (in [-1, 1]): the stick-slip plant."""
        return rhs(x, u, self.params, coulomb_sign=signs[..., 0])

    def fast_rhs(self, x: Tensor, u: Tensor) -> Tensor:
        """The batched training/reference path: the closed form is already the fastest."""
        return rhs(x, u, self.params)

    def residual(self, x: Tensor, dxdt: Tensor, u: Tensor, form: str = "explicit") -> Tensor:
        """ODE residual; 'mass' is the paper's M-multiplied form, 'explicit' is dxdt - rhs."""
        if form == "explicit":
            return dxdt - rhs(x, u, self.params)
        if form == "mass":
            return mass_residual(x, dxdt, u, self.params)
        raise ValueError(f"unknown residual form {form!r}; expected 'explicit' or 'mass'")
