"""Radau IIA collocation of the arm's inverse dynamics: the classical NMPC's transcription for stiff arms.

A period tau is split into `intervals` intervals of `stages` Radau IIA points each. The unknowns of stage k, z_k,
are the joint accelerations a_p at the period's points, point by point. Every point's position and velocity and the
period's end state are linear in (x_k, z_k) (velocities integrate accelerations and positions velocities, both by the
method's weights), so the dynamics constraint x_{k+1} = E_x x_k + E_z z_k + d is linear, and the only nonlinear
constraints are the inverse-dynamics residuals M(q_p) a_p + h(q_p, v_p) - tau_act(q_p, v_p, u_k) = 0: no M^-1.
One per-point function (the residual, and its Jacobian, in SX) is mapped over a period's points, a period function
(MX) assembles the residuals' Jacobian from the per-point blocks and the linear maps, and that is mapped over the
horizon: the generated C holds the rigid-body algorithm once, whatever the horizon.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import casadi as ca
import numpy as np

from pinnmpc.controller.classical.ocp import Blocks, CasadiOCP, Stages, whole_number
from pinnmpc.controller.limits import JointLimits

NEWTON_ITERATIONS = 12  # Newton steps of the one-period map F from zero accelerations (smooth periods converge
#   to rounding in 4-10; where sign(v) friction switches inside the period it may not converge at all)
POLISH_ITERATIONS = 2  # Newton steps of the estimator's prediction from the plan's accelerations (already close)


def radau_tableau(stages: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Butcher tableau (A, b, c) of the s-stage Radau IIA method: order 2 s - 1, L-stable, b = A's last row."""
    c = np.array(ca.collocation_points(stages, "radau"), dtype=np.float64)
    A = np.zeros((stages, stages))
    for j in range(stages):
        others = np.delete(c, j)
        lagrange = np.poly1d(np.poly(others) / np.prod(c[j] - others))  # 1 at c_j, 0 at the other points
        integral = np.polyint(lagrange)
        A[:, j] = integral(c) - integral(0.0)
    return A, A[-1].copy(), c


def period_maps(stages: int, intervals: int, tau: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The linear part of one period, as coefficients in the basis (q_0, v_0, a_1..a_P): of each point's position
    (P, 2 + P) and velocity (P, 2 + P), and of the end position and velocity (2, 2 + P)."""
    A, b, c = radau_tableau(stages)
    h, points = tau / intervals, stages * intervals
    basis = np.eye(2 + points)
    q, v = basis[0], basis[1]  # the current interval's start
    cq, cv = np.zeros((points, 2 + points)), np.zeros((points, 2 + points))
    for m in range(intervals):
        acc = basis[2 + m * stages : 2 + (m + 1) * stages]
        rows = slice(m * stages, (m + 1) * stages)
        cv[rows] = v + h * A @ acc
        cq[rows] = q + h * np.outer(c, v) + h * h * A @ A @ acc
        q, v = q + h * v + h * h * b @ A @ acc, v + h * b @ acc
    return cq, cv, np.vstack([q, v])


def inverse_dynamics(system: Any, coulomb_width: float | None = None) -> ca.Function:
    """r(q, v, a, u) = M(q) a + h(q, v) - tau_act(q, v, u) of the system: its casadi_inverse_dynamics (every arm of
    pinnmpc.systems gives one; a user's System without it: a - f(x, u)'s accelerations).

    coulomb_width: sign(v) friction smoothed as tanh(v / width), as system.casadi_rhs(width) smooths it."""
    if coulomb_width is not None and not coulomb_width > 0:
        raise ValueError(f"controller.coulomb_width={coulomb_width!r}; expected a number > 0 (rad/s) or null")
    width = () if coulomb_width is None else (coulomb_width,)
    own = getattr(system, "casadi_inverse_dynamics", None)
    if own is not None:
        return own(*width)
    nq = system.nq
    q, v, a, u = (ca.SX.sym(name, n) for name, n in (("q", nq), ("v", nq), ("a", nq), ("u", len(system.input_names))))
    r = a - system.casadi_rhs(*width)(ca.vertcat(q, v), u)[nq:]
    return ca.Function(f"{system.name}_inverse_dynamics", [q, v, a, u], [r], ["q", "v", "a", "u"], ["r"], {"cse": True})


def period_functions(point: ca.Function, cq: np.ndarray, cv: np.ndarray) -> tuple[ca.Function, ca.Function]:
    """res(x, u, z): one period's residuals (point by point), and jac(x, u, z) = (res, dres/dx, dres/du, dres/dz),
    assembled from the per-point Jacobian: dres_p/d(.) = R_q,p dq_p/d(.) + R_v,p dv_p/d(.) (+ R_a,p on a_p)."""
    nq, nu, points = point.size1_in(0), point.size1_in(3), cq.shape[0]
    q, v, a, u = (ca.SX.sym(n, point.size1_in(i)) for i, n in enumerate(("q", "v", "a", "u")))
    r = point(q, v, a, u)
    derivatives = [ca.jacobian(r, s) for s in (q, v, a, u)]
    point_jac = ca.Function(f"{point.name()}_jac", [q, v, a, u], [r, *derivatives], {"cse": True})
    x, um, z = ca.MX.sym("x", 2 * nq), ca.MX.sym("u", nu), ca.MX.sym("z", nq * points)
    acc = ca.reshape(z, nq, points)

    def at_points(coef: np.ndarray) -> Any:
        """Positions or velocities at the points (nq, P) from their coefficients."""
        return x[:nq] @ ca.DM(coef[:, 0]).T + x[nq:] @ ca.DM(coef[:, 1]).T + acc @ ca.DM(coef[:, 2:]).T

    def lifted(coef: np.ndarray) -> ca.DM:
        """A coefficient block as the matrix on joint vectors (kron with the identity), zeros dropped."""
        return ca.sparsify(ca.DM(np.kron(coef, np.eye(nq))))

    args = (at_points(cq), at_points(cv), acc, ca.repmat(um, 1, points))
    res = ca.Function("period_res", [x, um, z], [ca.vec(point.map(points)(*args))], ["x", "u", "z"], ["res"])
    rp, jq, jv, ja, ju = point_jac.map(points)(*args)
    diag = [ca.diagcat(*[j[:, p * nq : (p + 1) * nq] for p in range(points)]) for j in (jq, jv, ja)]
    dx = diag[0] @ lifted(cq[:, :2]) + diag[1] @ lifted(cv[:, :2])
    dz = diag[0] @ lifted(cq[:, 2:]) + diag[1] @ lifted(cv[:, 2:]) + diag[2]
    du = ca.vertcat(*[ju[:, p * nu : (p + 1) * nu] for p in range(points)])
    outs = [ca.vec(rp), dx, du, dz]
    jac = ca.Function("period_jac", [x, um, z], outs, ["x", "u", "z"], ["res", "dx", "du", "dz"])
    return res, jac


class RadauOCP(CasadiOCP):
    """The horizon OCP of CasadiOCP with Radau IIA collocation of the inverse dynamics instead of RK4 shooting."""

    transcription = "radau"

    def __init__(
        self,
        system: Any,
        horizon: int,
        Q: Sequence,
        R: Sequence,
        R_rate: Sequence | None,
        u_low: Sequence[float],
        u_high: Sequence[float],
        stages: int = 3,
        intervals: int = 1,
        joint_limits: JointLimits | Mapping | None = None,
        coulomb_width: float | None = None,
    ) -> None:
        for key, value in (("collocation_stages", stages), ("collocation_intervals", intervals)):
            if not whole_number(value):
                raise ValueError(f"controller.{key}={value!r}; expected a whole number >= 1")
        self.stages, self.intervals = int(stages), int(intervals)
        super().__init__(
            system, horizon, Q, R, R_rate, u_low, u_high, joint_limits=joint_limits, coulomb_width=coulomb_width
        )

    def _prepare(self, system: Any, rhs: ca.Function, coulomb_width: float | None, rk4_steps: int | None) -> None:
        """The per-point inverse dynamics, the period functions, the linear end-state map and the flow F."""
        nq = self.nx // 2
        self.rk4_steps = None
        self.nz = nq * self.stages * self.intervals
        cq, cv, end = period_maps(self.stages, self.intervals, self.tau)
        self.point = inverse_dynamics(system, coulomb_width)
        self.period_res, self.period_jac = period_functions(self.point, cq, cv)
        self.end_x = ca.sparsify(ca.DM(np.kron(end[:, :2], np.eye(nq))))  # x_end = end_x x_k + end_z z_k
        self.end_z = ca.sparsify(ca.DM(np.kron(end[:, 2:], np.eye(nq))))
        self.F = self._flow()

    def _newton(self, x: Any, u: Any, z: Any, iterations: int) -> Any:
        """The period's accelerations after Newton steps on its residuals from z (MX)."""
        for _ in range(iterations):
            res, _, _, dz = self.period_jac(x, u, z)
            z = z - ca.solve(dz, res, "qr")
        return z

    def _flow(self) -> ca.Function:
        """F(x, u): the collocation's one-period map, its residuals solved for the accelerations by Newton from zero."""
        x, u = ca.MX.sym("x", self.nx), ca.MX.sym("u", self.nu)
        z = self._newton(x, u, ca.MX.zeros(self.nz), NEWTON_ITERATIONS)
        return ca.Function("F", [x, u], [self.end_x @ x + self.end_z @ z], ["x", "u"], ["xf"])

    def flow_function(self) -> ca.Function:
        """flow(x, u, z): F(x, u) polished from the plan's accelerations z (the estimator's prediction, compiled)."""
        x, u, z = ca.MX.sym("x", self.nx), ca.MX.sym("u", self.nu), ca.MX.sym("z", self.nz)
        xf = self.end_x @ x + self.end_z @ self._newton(x, u, z, POLISH_ITERATIONS)
        return ca.Function("flow", [x, u, z], [xf], ["x", "u", "z"], ["xf"])

    @property
    def tag(self) -> str:
        """The transcription in a file name."""
        return f"radau{self.stages}x{self.intervals}"

    def describe(self) -> dict[str, Any]:
        """The transcription and its settings, for metrics.json."""
        return {
            "transcription": self.transcription,
            "collocation_stages": self.stages,
            "collocation_intervals": self.intervals,
        }

    def _model(self, s: Stages, jac: bool) -> tuple[list, list, list[Blocks], list[Blocks]]:
        """Per stage: the end state (linear), the residuals and, with jac, their blocks (from period_jac)."""
        horizon, nx, nu, nz = self.horizon, self.nx, self.nu, self.nz
        X, U, Z = ca.horzcat(*s.xs[:-1]), ca.horzcat(*s.us), ca.horzcat(*s.zs)
        nxt = self.end_x @ X + self.end_z @ Z
        nxts = [nxt[:, k] for k in range(horizon)]
        if not jac:
            res = self.period_res.map(horizon)(X, U, Z)
            return nxts, [res[:, k] for k in range(horizon)], [], []
        res, dx, du, dz = self.period_jac.map(horizon)(X, U, Z)
        ix, iu, iz = self.ix[:, 0], self.iu[:, 0], self.iz[:, 0]
        dnxt = [[(int(ix[k]), self.end_x), (int(iz[k]), self.end_z)] for k in range(horizon)]
        dres = [
            [
                (int(ix[k]), dx[:, k * nx : (k + 1) * nx]),
                (int(iu[k]), du[:, k * nu : (k + 1) * nu]),
                (int(iz[k]), dz[:, k * nz : (k + 1) * nz]),
            ]
            for k in range(horizon)
        ]
        return nxts, [res[:, k] for k in range(horizon)], dnxt, dres
