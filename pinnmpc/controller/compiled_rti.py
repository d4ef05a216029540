"""The network controller's real-time step after its network call, as one compiled function.

A warm real-time iteration of the lifted Gauss-Newton solver evaluates the network at the horizon's nodes (its
floor), then chains the linearised predictions along the horizon (shooting.linearise), forms the Gauss-Newton model
(HorizonOCP.gauss_newton_model) and takes the box step (box_step.newton_step): at batch 1 some hundred small numpy
calls, most of the controller's own time. Here the same arithmetic is one CasADi function of the network's values
and Jacobians (the weights, damping and horizon fixed), generated as C and called through CasADi's buffer API.
What it cannot finish alone is left to the numpy path with its outputs: a step a bound cuts short (the active-set
path, box_step.active_set_path) and a plan whose joint-limit penalty acts (HorizonOCP.gauss_newton_model). Whether it
acts is the C's answer too (JointLimits.reached on the linearisation's points and the states reached).
"""

from __future__ import annotations

import math

import casadi as ca
import numpy as np

from pinnmpc.controller.box_step import BOUND_TOL, active_set_path, newton_step
from pinnmpc.controller.limits import JointLimits
from pinnmpc.controller.ocp import HorizonOCP
from pinnmpc.systems.compiled import compile_functions

OUTPUTS = ("inputs", "states", "cost", "cut", "reach", "pred", "sens", "jtj", "hess", "grad", "fixed", "f")
POSITION = {name: k for k, name in enumerate(OUTPUTS)}  # each result's place in the result vector


KEPT = POSITION["sens"]  # the results before it (inputs, states, cost, cut, reach, pred) are copied out of the buffer


class RtiStep:
    """One compiled real-time step at batch 1 (rows of one): the step's result and, read only where a numpy finish
    needs them, its intermediates (each a view of the result vector, shaped when asked for). The results up to pred
    are its own copy; the intermediates after them view the compiled function's buffer, valid until its next call
    (compiled_step reads them at once): copying the Gauss-Newton matrices every sample would cost a large arm more
    than their rare use."""

    def __init__(self, out: np.ndarray, cuts: tuple[int, ...], horizon: int, nx: int, nu: int) -> None:
        head = out[: cuts[KEPT]].copy()
        self._out, self._head, self._cuts, self._dims = out, head, cuts, (horizon, nx, horizon * nu)
        out = head
        # what every step reads, as views made once (inputs, states, cost and cut lead OUTPUTS)
        self.inputs = out[cuts[0] : cuts[1]][None]  # (1, n) the inputs after the step
        self.states = out[cuts[1] : cuts[2]].reshape(1, horizon, nx)  # (1, H, nx) the linearised states they reach
        self.cost = out[cuts[2] : cuts[3]]  # (1,) the model's cost after the step
        self.cut = bool(out[cuts[3]] > 0.5)  # a bound cut the Newton step short: the active-set path must finish it
        reach = out[cuts[4] : cuts[5]]  # whether the predictions, and the states reached, meet a joint-limit penalty
        self.reach = (bool(reach[0] > 0.5), bool(reach[1] > 0.5))

    def _part(self, name: str) -> np.ndarray:
        """The result of that name (OUTPUTS), flat."""
        k = POSITION[name]
        return (self._head if k < KEPT else self._out)[self._cuts[k] : self._cuts[k + 1]]

    @property
    def pred(self) -> np.ndarray:
        """(1, H, nx) the linearised predictions at the current inputs."""
        return self._part("pred").reshape(1, *self._dims[:2])

    @property
    def sens(self) -> np.ndarray:
        """(1, H nx, n) their sensitivities to the inputs."""
        h, nx, n = self._dims
        return self._part("sens").reshape(1, h * nx, n)

    @property
    def jtj(self) -> np.ndarray:
        """(1, n, n) J^T J of the Gauss-Newton model."""
        return self._part("jtj").reshape(1, self._dims[2], self._dims[2])

    @property
    def hess(self) -> np.ndarray:
        """(1, n, n) the same, damped."""
        return self._part("hess").reshape(1, self._dims[2], self._dims[2])

    @property
    def grad(self) -> np.ndarray:
        """(1, n) the cost's gradient."""
        return self._part("grad")[None]

    @property
    def fixed(self) -> np.ndarray:
        """(1, n) bool: the inputs held at a bound."""
        return self._part("fixed")[None] > 0.5

    @property
    def f(self) -> np.ndarray:
        """(1,) the model's cost at the current inputs."""
        return self._part("f")


def step_flops(horizon: int, nx: int, nu: int, w_q: np.ndarray) -> int:
    """The compiled step's arithmetic, roughly: its Gauss-Newton matrix, its chain and its solve (multiply-adds).
    Its C has no BLAS, numpy's path costs mostly per call: past some size numpy's is the faster
    (LiftedGaussNewtonSolver.compiled_max_flops)."""
    n, weighted = horizon * nu, int(np.count_nonzero(np.abs(np.asarray(w_q)).sum(-1)))
    return horizon * weighted * n * n + horizon * nx * nx * n + n**3


def _blocks(v: ca.MX, count: int, rows: int, cols: int) -> list[ca.MX]:
    """count row-major (rows, cols) blocks of a flat C-ordered vector, as matrices."""
    size = rows * cols
    return [ca.reshape(v[k * size : (k + 1) * size], cols, rows).T for k in range(count)]


def spd_solve(n: int) -> ca.Function:
    """(a, b) -> a^-1 b for a symmetric positive definite a (n, n) as straight-line code: a Cholesky factor and two
    triangular solves, a third of a QR's arithmetic on the step's dense damped Gauss-Newton matrix. A matrix singular
    to rounding leaves NaN (compiled_step then finishes in numpy)."""
    a, b = ca.SX.sym("a", n, n), ca.SX.sym("b", n)
    r = ca.chol(a)  # upper triangular, a = r^T r
    return ca.Function("spd_solve", [a, b], [ca.solve(r, ca.solve(r.T, b))], {"cse": True})


def reaches(x: ca.MX, horizon: int, nx: int, limits: JointLimits | None) -> ca.MX:
    """1 where any of the stacked states x (H nx, positions first) lies where the joint-limit penalty acts, else 0:
    JointLimits.reached's arithmetic (the lookahead along a velocity towards a limit), infinite sides left out."""
    if limits is None or not limits.joints.size:
        return ca.MX(1, 1)
    states = ca.reshape(x, nx, horizon)  # column i: state i
    nq, joints, (low, high) = len(limits.low), limits.joints.tolist(), limits.inner
    q, v = states[joints, :], states[[nq + j for j in joints], :]
    flags = []
    for side, towards, beyond in ((low, ca.fmin, ca.lt), (high, ca.fmax, ca.gt)):
        ahead = q + limits.lookahead * towards(v, 0) if limits.lookahead else q
        for k, value in enumerate(side):
            if np.isfinite(value):
                flags.append(ca.mmax(beyond(ahead[k, :], float(value))))
    return ca.mmax(ca.vertcat(*flags)) if flags else ca.MX(1, 1)


def rti_function(
    horizon: int,
    nx: int,
    nu: int,
    w_q: np.ndarray,
    jac_u: np.ndarray,
    w_d: np.ndarray | None,
    damping: float,
    limits: JointLimits | None = None,
) -> ca.Function:
    """(y, a, b, nodes, U, ref, u_prev, lo, hi) -> OUTPUTS, every argument and result a flat C-ordered row: the
    arithmetic of linearise, gauss_newton_model (without joint limits), newton_step and the step's clipping, and
    whether the predictions and the states reached meet the limits' penalty (reaches)."""
    n = horizon * nu
    y, a, b = ca.MX.sym("y", horizon * nx), ca.MX.sym("a", horizon * nx * nx), ca.MX.sym("b", horizon * nx * nu)
    nodes, U, ref = ca.MX.sym("nodes", horizon * nx), ca.MX.sym("U", n), ca.MX.sym("ref", horizon * nx)
    u_prev, lo, hi = ca.MX.sym("u_prev", nu), ca.MX.sym("lo", n), ca.MX.sym("hi", n)
    ys, xs, rs = (_blocks(v, horizon, nx, 1) for v in (y, nodes, ref))
    As, Bs = _blocks(a, horizon, nx, nx), _blocks(b, horizon, nx, nu)
    # the chain x_i = y_i + A_i (x_{i-1} - s_i) and its sensitivities to every input, by forward substitution
    chain = []
    for i in range(horizon):
        direct = ca.horzcat(ca.MX(nx, i * nu), Bs[i], ca.MX(nx, (horizon - i - 1) * nu))
        column = ys[i] - (As[i] @ xs[i] if i else 0)
        rhs = ca.horzcat(direct, column)
        chain.append(rhs if not i else As[i] @ chain[-1] + rhs)
    pred = ca.vertcat(*(c[:, -1] for c in chain))
    sens = ca.vertcat(*(c[:, :-1] for c in chain))
    # the Gauss-Newton model: state residuals through the chain, input residuals linear in U
    wq = ca.sparsify(ca.DM(w_q))  # weights are mostly diagonal: their zeros cost no arithmetic
    sq = ca.vertcat(*(wq @ c[:, :-1] for c in chain))
    rx = ca.vertcat(*(wq @ (chain[i][:, -1] - rs[i]) for i in range(horizon)))
    ju = ca.sparsify(ca.DM(jac_u))
    ru = ju @ U
    if w_d is not None:  # the first rate residual holds u_prev: u_0 - u_prev
        rows = jac_u.shape[0]
        ru -= ca.vertcat(ca.MX(n, 1), ca.DM(w_d) @ u_prev, ca.MX(rows - n - w_d.shape[0], 1))
    jtj = sq.T @ sq + ca.sparsify(ca.DM(jac_u.T @ jac_u))
    grad = 2.0 * (sq.T @ rx + ju.T @ ru)
    f = ca.dot(rx, rx) + ca.dot(ru, ru)
    # the box step: inputs at a bound with the gradient pointing out are held, the rest take the Newton step
    tol = BOUND_TOL * (hi - lo)
    fixed = ca.logic_or(ca.logic_and(U - lo <= tol, grad > 0), ca.logic_and(hi - U <= tol, grad < 0))
    free = 1 - fixed
    hess = jtj + damping * ca.fmax(ca.sum1(ca.diag(jtj)) / n, 1e-30) * ca.MX.eye(n)
    masked = hess * (free @ free.T) + ca.diag(fixed)
    delta = spd_solve(n)(masked, -0.5 * grad * free)
    moved = U + delta
    cut = ca.mmax(free * ca.logic_or(moved > hi, moved < lo))
    predicted = -ca.dot(delta, grad + jtj @ delta)
    step = ca.fmin(ca.fmax(moved, lo), hi) - U
    states = pred + sens @ step
    reach = ca.vertcat(reaches(pred, horizon, nx, limits), reaches(states, horizon, nx, limits))
    outs = [U + step, states, f - predicted, cut, reach, pred]  # stacked (H nx) columns: the C order of (H, nx)
    outs += [_c_order(sens), _c_order(jtj), _c_order(hess), grad, fixed, f]
    args = [y, a, b, nodes, U, ref, u_prev, lo, hi]
    return ca.Function("rti_step", args, [ca.densify(o) for o in outs], {"cse": True})


def _c_order(m: ca.MX) -> ca.MX:
    """A matrix as its C-ordered (row-major) flat vector."""
    return ca.vec(m.T)


class CompiledRti:
    """The compiled real-time step of one OCP (horizon, weights, damping, joint limits), built once and cached by its
    C. Its arguments go in as one vector and its results come out as one (a call per argument through CasADi's buffer
    API costs as much as the arithmetic of a small arm's step), both buffers kept."""

    def __init__(
        self,
        horizon: int,
        nx: int,
        nu: int,
        weights: tuple,
        jac_u: np.ndarray,
        damping: float,
        limits: JointLimits | None = None,
    ) -> None:
        w_q, _, w_d = weights
        self.horizon, self.nx, self.nu = horizon, nx, nu
        f = rti_function(horizon, nx, nu, np.asarray(w_q), np.asarray(jac_u), w_d, float(damping), limits)
        name = f"rti_step_{horizon}x{nx}x{nu}"  # the compiled cache tells weights apart by the C's hash
        self.f = compile_functions(name, [_packed(f)], opt="-O3")["rti_packed"]
        self.cuts_out = tuple(int(c) for c in np.cumsum([0, *(f.numel_out(j) for j in range(f.n_out()))]))
        self._in = np.empty(sum(f.numel_in(i) for i in range(f.n_in())))
        self._out = np.empty(self.cuts_out[-1])
        self._buffer, self._evaluate = self.f.buffer()
        self._buffer.set_arg(0, memoryview(self._in))
        self._buffer.set_res(0, memoryview(self._out))

    def __call__(
        self,
        ynet: tuple[np.ndarray, ...],
        nodes: np.ndarray,
        U: np.ndarray,
        ref: np.ndarray,
        u_prev: np.ndarray,
        lo: np.ndarray,
        hi: np.ndarray,
    ) -> RtiStep:
        """One step for one problem: the network's (y, A, B) at the nodes (1, H, ...), the rest as the lifted solver
        holds them (rows of one)."""
        np.concatenate([v.reshape(-1) for v in (*ynet, nodes, U, ref, u_prev, lo, hi)], out=self._in)
        self._evaluate()
        return RtiStep(self._out, self.cuts_out, self.horizon, self.nx, self.nu)


def _packed(f: ca.Function) -> ca.Function:
    """f with its arguments stacked into one vector and its results into one, in order."""
    z = ca.MX.sym("z", sum(f.numel_in(i) for i in range(f.n_in())))
    args, start = [], 0
    for i in range(f.n_in()):
        args.append(z[start : start + f.numel_in(i)])
        start += f.numel_in(i)
    outs = f(*args)
    return ca.Function("rti_packed", [z], [ca.densify(ca.vertcat(*(ca.vec(o) for o in outs)))])


def compiled_step(
    compiled: CompiledRti,
    ocp: HorizonOCP,
    nodes: np.ndarray,
    U: np.ndarray,
    data: tuple,
    damping: float,
    prior: np.ndarray | None = None,
    prior_reached: bool | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool, bool | None]:
    """One real-time lifted step of one problem as LiftedGaussNewtonSolver._rti_steps takes it (inputs, the states
    they reach, the model's cost after the step): the network at the nodes, then the compiled step (built for the
    OCP's joint limits), finished in numpy where a bound cuts it short or a joint-limit penalty acts. data:
    (reference, u_prev, low, high) rows.
    Last, whether the states reached, or prior (the last plan's states, where given), lie where a joint-limit penalty
    acts, and whether the states reached do (None without limits): the compiled step's answers for its own points,
    prior_reached for prior where the step that planned it gave one."""
    refb, upb, lo, hi = data
    step = compiled(ocp.step_with_jacobian(nodes, U.reshape(1, ocp.horizon, ocp.nu)), nodes, U, refb, upb, lo, hi)
    limits = ocp.joint_limits  # the compiled step's own (LiftedGaussNewtonSolver._compiled keys them by it)
    at_points, at_states = (False, None) if limits is None else step.reach  # its C checked them
    at_prior = False
    if limits is not None and prior is not None:
        at_prior = bool(limits.reached(prior)[0]) if prior_reached is None else prior_reached
    solved = math.isfinite(step.cost[0])  # else its Cholesky factor broke down (spd_solve)
    if solved and not step.cut and not at_points:
        return step.inputs, step.states, step.cost, bool(at_states) or at_prior, at_states
    f, jtj, grad, hess, fixed = step.f, step.jtj, step.grad, step.hess, step.fixed
    if at_points:  # the penalty's rows join the model (the numpy path's own)
        f, jtj, grad = ocp.gauss_newton_model(step.pred, step.sens, U, refb, upb)
    if not solved or at_points:
        delta, _, predicted, _ = newton_step(jtj, grad, U, lo, hi, damping)
    else:
        delta = active_set_path(hess, grad, fixed, U, lo, hi)
        predicted = -np.einsum("bi,bi->b", delta, grad + np.matmul(jtj, delta[..., None])[..., 0])
    moved = np.clip(U + delta, lo, hi) - U
    states = step.pred + (step.sens @ moved[..., None])[..., 0].reshape(step.pred.shape)
    at_states = None if limits is None else bool(limits.reached(states)[0])
    return U + moved, states, f - predicted, bool(at_states) or at_prior, at_states
