"""The frozen-arm prior's Jacobian through an eigendecomposition, for arms where AD through its exponential is costly.

With Kh = kv^1/2 the prior's matrices are functions of one symmetric positive definite matrix S = Kh M(q0)^-1 Kh
(pinnmpc.surrogate.prior has the prior itself):

    E = exp(-M^-1 kv tau) = Kh^-1 f0(S) Kh,   kv^-1 M (I - E) = Kh^-1 f1(S) Kh,
    f0(l) = exp(-l tau),   f1(l) = (1 - exp(-l tau)) / l.

With S = V diag(l) V^T, a change dS of S changes f(S) by V (F o (V^T dS V)) V^T (Daleckii-Krein), F_ab the divided
difference (f(l_a) - f(l_b)) / (l_a - l_b) (f' where l_a = l_b). Along q0_j, dS = -Kh M^-1 (dM/dq0_j) M^-1 Kh, with
dM/dq0 from CasADi's AD of the arm's mass matrix compiled to C. This costs one eigendecomposition and a few small
matrix products per sample, where AD through a Taylor series with squarings carries n tangents through every
product: on a 7-joint arm the exponential needs many squarings (its time constants span 1 ms to 0.2 s against a
50 ms period), so this path is the cheaper there; small arms keep the AD one (docs/design.md).

With the Coriolis torques at the moving velocity (frozen_arm_moving) they are written through the same dM/dq0_k,
C(q0, w) w = (sum_k w_k dM_k) w - 1/2 (w^T dM_i w)_i (Christoffel symbols, one formula for all sub-steps), and
their change along q0_j through d2M/dq0_j dq0_k, computed once per sample: AD through the recursive Newton-Euler
graph at every sub-step's velocity cost several times more (docs/training-findings.md).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import casadi as ca
import numpy as np

if TYPE_CHECKING:
    from pinnmpc.systems import RigidArm

CLOSE = 1e-7  # eigenvalues closer than this (relative) share a divided difference: f' at the first
OPT = "-O3"  # C optimisation level of both functions: the factored sub-steps run fastest at -O3, the settled
#   form alike at -O2 and -O3, at about the same compile time (docs/results.md)


def divided_differences(lam: list, f: list, df: list) -> ca.SX:
    """Divided differences F_ab of one function with values f and derivatives df at the eigenvalues lam."""
    n = len(lam)
    out = ca.SX(n, n)
    for a in range(n):
        for b in range(n):
            if a == b:
                out[a, b] = df[a]
                continue
            gap = lam[a] - lam[b]
            close = ca.fabs(gap) <= CLOSE * ca.fabs(lam[a])
            out[a, b] = ca.if_else(close, df[a], (f[a] - f[b]) / ca.if_else(close, 1, gap))
    return out


class EigenPriorJacobian:
    """x_p(tau) and its Jacobian d x_p / d(x0, u) (B, nx (nx + nu), row-major) for numpy rows x0 (B, nx), u (B, nu):
    S by one compiled function, its eigendecomposition by numpy, the rest by a second compiled function."""

    def __init__(
        self,
        arm: RigidArm,
        tau: float,
        kv: np.ndarray,
        steps: int = 0,
        coriolis: bool = False,
        suffix: str = "",
    ) -> None:
        """steps: sub-steps with the dry friction at the moving velocity (0: one solve); coriolis: the sub-steps hold
        C(q0, w) w too (ArmPrior.moving_torque); suffix: the compiled functions' name suffix."""
        from pinnmpc.systems.compiled import BatchedFunction, compile_functions

        n = self.n = arm.nq
        span = tau / max(1, steps)  # one solve over tau, or sub-steps with moving friction (ArmPrior.steps)
        kh = ca.DM(np.sqrt(kv))
        q, u, lam, vt = ca.SX.sym("q", n), ca.SX.sym("u", n), ca.SX.sym("lam", n), ca.SX.sym("v", n * n)
        x0 = ca.SX.sym("x", 2 * n)
        frozen = arm.casadi_frozen_terms(settled=not steps)  # (q, u) -> (M, c0), built once, called at q and q0
        m = frozen(q, u)[0]
        s_of_q = ca.mtimes(ca.diag(kh), ca.solve(m, ca.diag(kh)))  # S = Kh M^-1 Kh
        tag = f"{arm.name}_frozen_eigen{suffix}"
        spd = ca.Function(f"{tag}_s", [q], [ca.densify(ca.vec(s_of_q))], {"cse": True})
        # the rest at q = q0: V from its row-major rows (CasADi reshapes column-major, so those read as V^T)
        q0 = x0[:n]
        m, c0 = frozen(q0, u)
        vss = c0 / ca.DM(kv)
        vec = ca.reshape(vt, n, n).T
        em = [ca.expm1(-lam[a] * span) for a in range(n)]
        f0, f1 = [e + 1 for e in em], [-e / lam[a] for a, e in enumerate(em)]
        df0 = [-span * (e + 1) for e in em]
        df1 = [(lam[a] * span * (e + 1) + e) / lam[a] ** 2 for a, e in enumerate(em)]
        left, right = ca.mtimes(ca.diag(1 / kh), vec), ca.mtimes(vec.T, ca.diag(kh))  # Kh^-1 V and V^T Kh
        p = ca.solve(m, right.T).T  # V^T Kh M^-1, so V^T dS_j V = -p dM_j p^T
        lams = [lam[a] for a in range(n)]
        big0, big1 = divided_differences(lams, f0, df0), divided_differences(lams, f1, df1)
        factors = (left, right, p, big0, big1)
        if steps:
            diags = (ca.vertcat(*f0), ca.vertcat(*f1))
            solve = (vss, diags, ca.DM(kv), arm.dry_friction)
            xp, jac = _moving(n, (x0, u), solve, factors, (span, steps), m, coriolis)
        else:
            xp, jac = _settled((x0, u), (vss, f0, f1), factors, tau, m)
        rest = ca.Function(tag, [x0, u, lam, vt], [xp, ca.densify(ca.vec(jac.T))], {"cse": True})
        lib = compile_functions(tag, [spd, rest], opt=OPT)
        self.spd, self.rest = BatchedFunction(lib[spd.name()]), BatchedFunction(lib[rest.name()])

    def __call__(self, x0: np.ndarray, u: np.ndarray) -> list[np.ndarray]:
        """[x_p (B, nx), J (B, nx (nx + nu)) row-major], the CompiledPrior.with_jacobian contract."""
        n = self.n
        s = self.spd(x0[:, :n])[0].reshape(-1, n, n)  # symmetric: its column-major vec reads back as S
        lam, vec = np.linalg.eigh(s)
        return self.rest(x0, u, lam, vec.reshape(-1, n * n))


def _settled(inputs: tuple, solve: tuple, eigen: tuple, tau: float, m: ca.SX) -> tuple[ca.SX, ca.SX]:
    """x_p and its Jacobian for one exact solve over tau: x_p is linear in (v0, v_ss) given q0, and along q0_j the
    Daleckii-Krein derivatives of E and the lag are applied to V^T Kh (v0 - v_ss) alone. inputs (x0, u); solve (v_ss,
    f0, f1); eigen (Kh^-1 V, V^T Kh, V^T Kh M^-1, F0, F1)."""
    (x0, u), (vss, f0, f1), (left, right, p, big0, big1) = inputs, solve, eigen
    n = vss.shape[0]
    q0, v0 = x0[:n], x0[n:]
    e = ca.mtimes(ca.mtimes(left, ca.diag(ca.vertcat(*f0))), right)  # E
    lag = ca.mtimes(ca.mtimes(left, ca.diag(ca.vertcat(*f1))), right)  # kv^-1 M (I - E)
    d = v0 - vss
    z = ca.mtimes(right, d)  # V^T Kh (v0 - v_ss)
    cols0, cols1 = [], []
    for j in range(n):
        t = ca.mtimes(ca.mtimes(p, _dm(m, q0, j)), p.T)
        cols0.append(-ca.mtimes(left, ca.mtimes(big0 * t, z)))
        cols1.append(-ca.mtimes(left, ca.mtimes(big1 * t, z)))
    eye = ca.SX.eye(n)
    by_vss = ca.vertcat(tau * eye - lag, eye - e)
    by_q = ca.vertcat(eye + ca.horzcat(*cols1), ca.horzcat(*cols0)) + ca.mtimes(by_vss, ca.jacobian(vss, q0))
    jac = ca.horzcat(by_q, ca.vertcat(lag, e), ca.mtimes(by_vss, ca.jacobian(vss, u)))
    return ca.vertcat(q0 + vss * tau + ca.mtimes(lag, d), vss + ca.mtimes(e, d)), jac


def _moving(
    n: int, inputs: tuple, solve: tuple, eigen: tuple, steps: tuple, m: ca.SX, coriolis: bool
) -> tuple[ca.SX, ca.SX]:
    """x_p and its Jacobian for the friction sub-steps (pinnmpc.surrogate.prior.friction_substeps), E and the lag
    applied in factored form, Kh^-1 V (diag f - F o D) V^T Kh with D = -V^T dS V: D = 0 gives their values, and
    CasADi's forward mode along D = p dM_j p^T their derivative along q0_j (Daleckii-Krein) through every sub-step,
    no n x n matrix formed. With coriolis, each sub-step's C(q0, w) w enters linearised at its own point
    (HeldCoriolis). inputs (x0, u); solve (v_ss, (f0, f1), kv, w -> the dry friction); eigen (Kh^-1 V, V^T Kh,
    V^T Kh M^-1, F0, F1); steps (h, count)."""
    from pinnmpc.surrogate.substeps import friction_substeps

    (x0, u), (vss, (f0, f1), kv, dry), (left, right, p, big0, big1), (h, count) = inputs, solve, eigen, steps
    q0 = x0[:n]
    turn = ca.SX.sym("d", n, n)  # -V^T dS V, zero at the point itself
    held = HeldCoriolis(n, q0) if coriolis else None

    def relax(d: ca.SX) -> tuple[ca.SX, ca.SX]:
        """kv^-1 M (I - E) d and E d."""
        r = ca.mtimes(right, d)
        return ca.mtimes(left, f1 * r - ca.mtimes(big1 * turn, r)), ca.mtimes(left, f0 * r - ca.mtimes(big0 * turn, r))

    torque = (lambda w: dry(w) + held(w)) if held else dry  # noqa: E731
    xs = ca.vertcat(*friction_substeps((q0, x0[n:]), vss, torque, kv, h, relax, count))
    dms = [ca.densify(_dm(m, q0, j)) for j in range(n)]
    seeds = [ca.vec(ca.mtimes(ca.mtimes(p, dms[j]), p.T)) for j in range(n)]  # -V^T dS_j V
    by_q = ca.jtimes(xs, ca.vec(turn), ca.horzcat(*seeds))  # forward mode along each q0_j
    out = [xs, ca.jacobian(xs, ca.vertcat(x0, u)) + ca.horzcat(by_q, ca.SX(2 * n, 2 * n))]
    if held:
        out = held.resolve(out, dms)
    return tuple(ca.substitute(out, [turn], [ca.SX.zeros(n, n)]))


class HeldCoriolis:
    """C(q0, w) w of the sub-steps for AD at the cost of its linearisation. In Christoffel form each torque is a
    quadratic form in w, c_i = w^T A_i w with A_i[k, l] = dM_il/dq0_k - 1/2 dM_kl/dq0_i, and its derivative along q0_j
    the same with d2M; both sets of forms are computed once per sample, packed over the pairs k <= l. Each call at an
    expression w returns c(w') + J(w') (w - w') + G(w') (q0 - q0'), w' and q0' symbols resolved to w and q0 after
    differentiation, J = dc/dw', G_ij = dc_i/dq0_j: equal in value, exact in derivative, and AD carries each tangent
    through two n x n products instead of the n^3 form; the forms are symbols until then too."""

    def __init__(self, n: int, q0: ca.SX) -> None:
        self.n, self.q0, self.q_at = n, q0, ca.SX.sym("q_at", n)
        self.pairs = [(k, m) for k in range(n) for m in range(k, n)]
        self.forms = ca.SX.sym("forms", n, len(self.pairs))  # row i: c_i's packed form
        self.slopes = ca.SX.sym("slopes", n * n, len(self.pairs))  # row i n + j: dc_i/dq0_j's
        self.points: list[tuple[ca.SX, ca.SX]] = []  # (w', the expression it stands for), in call order

    def __call__(self, w: ca.SX) -> ca.SX:
        """The linearised C(q0, w) w, w' a new symbol for this w."""
        n = self.n
        at = ca.SX.sym(f"w_at{len(self.points)}", n)
        self.points.append((at, w))
        products = ca.vertcat(*[at[k] * at[m] for k, m in self.pairs])
        c = ca.mtimes(self.forms, products)
        g = ca.reshape(ca.mtimes(self.slopes, products), n, n).T  # column-major: row i n + j reads back as G_ij
        return c + ca.mtimes(ca.jacobian(c, at), w - at) + ca.mtimes(g, self.q0 - self.q_at)

    def resolve(self, exprs: list[ca.SX], dms: list[ca.SX]) -> list[ca.SX]:
        """exprs with every symbol put back: each w' by its expression in call order (a later one holds earlier
        w'), then q0' and the forms from dM/dq0 and d2M/dq0 dq0 (AD of the mass matrix's first derivatives)."""
        defs = [w for _, w in self.points]
        for i, (at, _) in enumerate(self.points):
            done = ca.substitute([*exprs, *defs[i + 1 :]], [at], [defs[i]])
            exprs, defs[i + 1 :] = done[: len(exprs)], done[len(exprs) :]
        n, q0 = self.n, self.q0
        second = {}
        for k in range(n):
            for j in range(k, n):
                second[k, j] = second[j, k] = ca.densify(_dm(dms[k], q0, j))
        forms = self._packed(dms)
        along = [self._packed([second[k, j] for k in range(n)]) for j in range(n)]  # per q0_j: every c_i's form
        slopes = ca.vertcat(*[along[j][i, :] for i in range(n) for j in range(n)])
        return ca.substitute(exprs, [self.q_at, self.forms, self.slopes], [q0, forms, slopes])

    def _packed(self, d: list[ca.SX]) -> ca.SX:
        """Rows i: A_i[k, l] = d[k]_il - 1/2 d[i]_kl over the pairs k <= l, off-diagonal pairs taking A_kl + A_lk."""
        n = self.n

        def a(i: int, k: int, m: int) -> ca.SX:
            """A_i[k, m]."""
            return d[k][i, m] - 0.5 * d[i][k, m]

        rows = [[a(i, k, m) + a(i, m, k) if k != m else a(i, k, k) for k, m in self.pairs] for i in range(n)]
        return ca.vertcat(*[ca.horzcat(*row) for row in rows])


def _dm(m: ca.SX, q: ca.SX, j: int) -> ca.SX:
    """dM/dq_j as an n x n matrix."""
    n = m.shape[0]
    return ca.reshape(ca.jacobian(ca.vec(m), q[j]), n, n)
