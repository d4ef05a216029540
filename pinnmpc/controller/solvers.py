"""Solvers for the batched box-constrained horizon OCP: the paper's RMSprop, L-BFGS, and a fast Gauss-Newton."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Protocol

import numpy as np
import torch
from torch import Tensor

from pinnmpc.controller.ocp import HorizonOCP

BOUND_TOL = 1e-12  # relative to the box width: closer than this to a bound counts as on it


def _project(u: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Clip to the box and put values within rounding of a bound exactly on it (the answer a user sees)."""
    tol = BOUND_TOL * (hi - lo)
    u = np.clip(u, lo, hi)
    return np.where(u - lo <= tol, lo, np.where(hi - u <= tol, hi, u))


def _result(shape: tuple[int, ...], U, iterations, cost, converged, sens):  # noqa: ANN001, ANN202
    """A solve's outputs in the problems' own batch shape."""
    lead = shape[:-2]
    return U.reshape(shape), iterations.reshape(lead), cost.reshape(lead), converged.reshape(lead), sens


@dataclass
class SolveInfo:
    """Per-problem solver statistics, batched like the problems."""

    iterations: Tensor  # (B,) int
    cost: Tensor  # (B,) float
    converged: Tensor  # (B,) bool
    sensitivities: np.ndarray | None = None  # (B, H, nx, H*nu) d x_i / d U near the solution, for the next solve


class Solver(Protocol):
    """Minimise the OCP over U (B, H, nu) within [low, high], starting from U0.

    array_api names the array library the solver works in ("torch" or "numpy"): NMPC.make_step
    hands it arrays of that kind, so batch-1 solves pay no conversions. Solvers with accepts_prior
    take prior= (the last solve's SolveInfo.sensitivities) to warm-start their Jacobian too.
    """

    array_api: str

    def solve(
        self,
        ocp: HorizonOCP,
        x0: Tensor,
        U0: Tensor,
        x_ref: Tensor,
        u_prev: Tensor,
        low: Tensor,
        high: Tensor,  # noqa: N803
    ) -> tuple[Tensor, SolveInfo]:
        """Return the optimised inputs and statistics."""
        ...


@dataclass
class RMSpropSolver:
    """The paper's solver: RMSprop on the inputs, clamped to the box after every step."""

    lr: float = 0.01  # RMSprop learning rate
    max_iter: int = 1000  # iteration cap (paper: 1000)
    tol: float = 1e-8  # stop when the summed cost changes less than this (paper: 1e-8)
    array_api: ClassVar[str] = "torch"

    def solve(self, ocp, x0, U0, x_ref, u_prev, low, high):  # noqa: ANN001, ANN201, N803
        """Projected first-order descent with autograd gradients."""
        U = U0.clone().requires_grad_(True)  # noqa: N806
        opt = torch.optim.RMSprop([U], lr=self.lr)
        prev = float("inf")
        it = 0
        for it in range(1, self.max_iter + 1):  # noqa: B007
            opt.zero_grad()
            cost = ocp.cost(x0, U, x_ref, u_prev).sum()
            cost.backward()
            opt.step()
            with torch.no_grad():
                U.copy_(torch.maximum(torch.minimum(U, high), low))
            if abs(prev - float(cost.detach())) < self.tol:
                break
            prev = float(cost.detach())
        U = U.detach()  # noqa: N806
        with torch.no_grad():
            final = ocp.cost(x0, U, x_ref, u_prev)
        converged = torch.full(final.shape, it < self.max_iter)
        return U, SolveInfo(torch.full(final.shape, it), final, converged)


@dataclass
class LBFGSSolver:
    """torch.optim.LBFGS on the inputs, projected onto the box between rounds."""

    max_iter: int = 20  # L-BFGS iterations per round
    rounds: int = 5  # projection rounds
    tol: float = 1e-12  # stop when a round changes the summed cost less than this
    array_api: ClassVar[str] = "torch"

    def solve(self, ocp, x0, U0, x_ref, u_prev, low, high):  # noqa: ANN001, ANN201, N803
        """Quasi-Newton with strong Wolfe line search and clamping."""
        U = U0.clone().requires_grad_(True)  # noqa: N806
        opt = torch.optim.LBFGS([U], lr=1.0, max_iter=self.max_iter, line_search_fn="strong_wolfe")
        evals = [0]

        def closure() -> Tensor:
            opt.zero_grad()
            cost = ocp.cost(x0, U, x_ref, u_prev).sum()
            cost.backward()
            evals[0] += 1
            return cost

        prev = float("inf")
        for _ in range(self.rounds):
            cost = float(opt.step(closure).detach())
            with torch.no_grad():
                U.copy_(torch.maximum(torch.minimum(U, high), low))
            if abs(prev - cost) < self.tol * max(1.0, abs(cost)):
                break
            prev = cost
        U = U.detach()  # noqa: N806
        with torch.no_grad():
            final = ocp.cost(x0, U, x_ref, u_prev)
        return U, SolveInfo(torch.full(final.shape, evals[0]), final, torch.ones(final.shape, dtype=torch.bool))


@dataclass
class GaussNewtonSolver:
    """Projected Gauss-Newton / Levenberg-Marquardt on the least-squares structure, batched, in numpy.

    Jacobians come from forward-mode tangents through the network; bounds are handled
    by an active set (variables at a bound whose gradient points outward are frozen)
    and projection; the step length is the best of a few candidates evaluated in one
    batched rollout. numpy, because batch-1 solves are dominated by per-op overhead.
    """

    max_iter: int = 30  # iteration cap
    tol_grad: float = 1e-9  # converged when the projected gradient's max-norm is below this
    tol_cost: float = 1e-10  # ... or the relative cost decrease predicted (or achieved) is below this
    tol_gap: float = 1e-8  # ... or the decrease still to come, extrapolated from the last two, is below this x cost
    damping: float = 1e-9  # Levenberg-Marquardt damping, relative to the mean diagonal of J^T J
    step_lengths: tuple[float, ...] = (1.0, 0.5, 0.25, 0.1, 0.01)  # tried first alone, then the rest at once
    reuse_jacobian: bool = True  # receding horizon: the first step reuses the last solve's sensitivities, shifted
    array_api: ClassVar[str] = "numpy"  # also accepts torch tensors (and then returns them)
    accepts_prior: ClassVar[bool] = True

    def __post_init__(self) -> None:
        self.alphas = np.asarray(self.step_lengths, dtype=np.float64)
        if self.alphas.ndim != 1 or self.alphas.size == 0 or np.any(self.alphas <= 0):
            raise ValueError(f"step_lengths must be a non-empty list of positive numbers, got {self.step_lengths}")

    def solve(self, ocp, x0, U0, x_ref, u_prev, low, high, prior=None):  # noqa: ANN001, ANN201
        """Accepts torch or numpy; returns the same kind.

        prior: SolveInfo.sensitivities of the previous receding-horizon solve when U0 is its plan shifted
        by one step; the first Gauss-Newton step then reuses them instead of a full Jacobian rollout.
        """
        as_torch = isinstance(U0, Tensor)
        args = [
            a.detach().numpy() if isinstance(a, Tensor) else np.asarray(a, dtype=np.float64)
            for a in (x0, U0, x_ref, u_prev, low, high)
        ]
        if prior is not None and (not self.reuse_jacobian or ocp.flow is None or ocp.horizon < 2):
            prior = None
        if prior is not None:
            prior = np.asarray(prior, dtype=np.float64)
            want = (int(np.prod(U0.shape[:-2])), ocp.horizon, ocp.nx, ocp.horizon * ocp.nu)
            if prior.shape != want:
                raise ValueError(f"prior sensitivities must have shape {want}, got {prior.shape}")
        U, iterations, cost, converged, sens = self._solve(ocp, *args, prior)
        if as_torch:
            info = SolveInfo(torch.from_numpy(iterations), torch.from_numpy(cost), torch.from_numpy(converged), sens)
            return torch.from_numpy(U), info
        return U, SolveInfo(iterations, cost, converged, sens)

    def _solve(self, ocp, x0, U0, x_ref, u_prev, low, high, prior):  # noqa: ANN001, ANN202
        """Iterate until every problem has converged or max_iter is reached.

        The first two line searches evaluate their candidates with Jacobians, so the accepted one's is
        there for the next step; later ones evaluate the cost only and take a Jacobian just for the
        problems that go on. A problem stops when the Gauss-Newton model predicts a relative decrease
        below tol_cost, when its projected gradient vanishes, when the decrease still to come (extrapolated
        from the last three) is below tol_gap, or when no candidate improves.
        """
        shape = U0.shape
        n = shape[-1] * shape[-2]
        x0b, refb = x0.reshape(-1, x0.shape[-1]), x_ref.reshape(-1, *x_ref.shape[-2:])
        upb = u_prev.reshape(-1, shape[-1])
        U = np.clip(U0, low, high).reshape(-1, n)
        lo, hi = np.broadcast_to(low, shape).reshape(-1, n), np.broadcast_to(high, shape).reshape(-1, n)
        batch = U.shape[0]
        r, jac, sens = self._jacobian(ocp, x0b, U, refb, upb, prior)
        cost = np.einsum("bm,bm->b", r, r)
        running = np.ones(batch, dtype=bool)
        iterations = np.zeros(batch, dtype=np.int64)
        decreases = np.full((batch, 2), np.inf)  # the two previous decreases, latest first
        for k in range(self.max_iter):
            # views while every problem runs (the batch-1 case), copies of the running rows otherwise
            idx = slice(None) if running.all() else np.flatnonzero(running)
            u_i, f = U[idx], cost[idx].copy()  # f must survive the update of cost below
            delta, pgrad_max, predicted = self._step(r[idx], jac[idx], u_i, lo[idx], hi[idx])
            done = (pgrad_max < self.tol_grad) | (predicted <= self.tol_cost * np.maximum(f, 1e-300))
            if k == 0 and prior is not None:
                done[:] = False  # an approximate Jacobian cannot certify convergence
            rows = np.arange(batch)[idx]
            running[rows[done]] = False
            if done.all():
                break
            go = ~done
            if not done.any():
                go = slice(None)
            rows, u_i, f, delta = rows[go], u_i[go], f[go], delta[go]
            first = k < 2  # the first two steps rarely stop (no extrapolation yet), so take their Jacobians along
            best_c, new_u, new_r, new_jac, new_sens = self._line_search(
                ocp, x0b[rows], refb[rows], upb[rows], u_i, delta, f, lo[rows], hi[rows], with_jacobian=first
            )
            improved = best_c < f
            acc = rows[improved]
            U[acc], cost[acc] = new_u[improved], best_c[improved]
            if first:
                r[acc], jac[acc] = new_r[improved], new_jac[improved]
                if sens is not None:
                    sens[acc] = new_sens[improved]
            iterations[rows] += 1
            decrease = f - best_c
            stop = ~improved | (decrease <= self.tol_cost * np.maximum(f, 1e-300))
            stop |= self._remaining(decrease, decreases[rows]) <= self.tol_gap * best_c
            decreases[rows] = np.stack((decrease, decreases[rows, 0]), -1)
            running[rows[stop]] = False
            more = rows[~stop]
            if not first and more.size:
                r[more], jac[more], more_sens = self._jacobian(ocp, x0b[more], U[more], refb[more], upb[more])
                if sens is not None:
                    sens[more] = more_sens
            if not running.any():
                break
        return _result(shape, _project(U, lo, hi), iterations, cost, ~running, sens)

    def _jacobian(self, ocp, x0, U, x_ref, u_prev, prior=None):  # noqa: ANN001, ANN202
        """Residuals, Jacobian and (numpy surrogates) the state sensitivities that a later solve may reuse."""
        if ocp.flow is not None and self.reuse_jacobian:
            return ocp.jacobian_rollout(x0, U, x_ref, u_prev, prior)
        r, jac = ocp.residuals_and_jacobian(x0, U.reshape(-1, ocp.horizon, ocp.nu), x_ref, u_prev)
        return r, jac, None

    @staticmethod
    def _remaining(decrease: np.ndarray, previous: np.ndarray) -> np.ndarray:
        """Cost decrease still to come, extrapolated geometrically from the last three decreases.

        Gauss-Newton converges at least linearly, so with rho the larger of the two latest ratios of
        successive decreases what remains is at most decrease * rho / (1 - rho); near a zero-residual
        optimum it converges quadratically and this overestimates. Two ratios, not one, because a step
        cut short by a bound gives one tiny decrease in an otherwise slow sequence. previous (B, 2)
        holds the two decreases before this one, latest first; infinite until three steps were taken.
        """
        with np.errstate(divide="ignore", invalid="ignore"):
            rho = np.maximum(decrease / previous[:, 0], previous[:, 0] / previous[:, 1])
            known = np.isfinite(previous).all(-1) & (rho < 1.0)
            return np.where(known, decrease * rho / (1.0 - rho), np.inf)

    def _step(self, r, jac, u, lo, hi):  # noqa: ANN001, ANN202
        """Gauss-Newton step within the box, by a primal active set on the (convex) Gauss-Newton model.

        Variables at a bound with the gradient pointing out start fixed. From there the free variables
        move along the model's Newton direction until one of them meets a bound; that one is fixed and
        the path goes on, until a full Newton step stays inside (at most n segments, usually one).
        The model decreases along every segment. Returns the step, the projected gradient's max-norm and
        the cost decrease the model predicts for the step.
        """
        jt = jac.swapaxes(-1, -2)
        grad = 2.0 * np.matmul(jt, r[..., None])[..., 0]
        tol = BOUND_TOL * (hi - lo)  # "at a bound" up to rounding: steps aimed at a bound land within it
        fixed = ((u - lo <= tol) & (grad > 0)) | ((hi - u <= tol) & (grad < 0))
        pgrad_max = np.abs(np.where(fixed, 0.0, grad)).max(-1)
        jtj = jt @ jac
        mu = self.damping * np.maximum(np.einsum("bii->b", jtj) / jtj.shape[-1], 1e-30)
        hess = jtj + mu[:, None, None] * np.eye(jtj.shape[-1])
        delta = self._masked_solve(hess, grad, fixed)
        if np.any(~fixed & ((u + delta > hi) | (u + delta < lo))):
            delta = self._active_set_path(hess, grad, fixed, u, lo, hi)
        jd = np.matmul(jac, delta[..., None])[..., 0]
        predicted = -np.einsum("bm,bm->b", jd, 2.0 * r + jd)  # ||r||^2 - ||r + J delta||^2
        return delta, pgrad_max, predicted

    def _active_set_path(self, hess, grad, fixed, u, lo, hi):  # noqa: ANN001, ANN202
        """Piecewise-linear path of the primal active-set method: Newton direction on the free variables,
        cut at the first bound it meets, which joins the fixed ones."""
        delta, fixed, done = np.zeros_like(u), fixed.copy(), np.zeros(u.shape[0], dtype=bool)
        for _ in range(u.shape[-1] + 1):
            model_grad = grad + 2.0 * np.matmul(hess, delta[..., None])[..., 0]
            direction = np.where(done[:, None], 0.0, self._masked_solve(hess, model_grad, fixed))
            room = np.where(direction > 0, hi - u - delta, lo - u - delta)
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = np.where(~fixed & (direction != 0), np.maximum(room / direction, 0.0), np.inf)
            first = ratio.min(-1)
            length = np.minimum(first, 1.0)
            delta += length[:, None] * direction
            fixed |= (ratio <= first[:, None]) & (first < 1.0)[:, None]
            done |= first >= 1.0
            if done.all():
                break
        return delta

    @staticmethod
    def _masked_solve(hess, grad, fixed):  # noqa: ANN001, ANN205
        """Newton direction of the model 1/2 d^T (2 hess) d + grad^T d on the free variables (0 on the fixed)."""
        if not fixed.any():
            return np.linalg.solve(hess, -0.5 * grad[..., None])[..., 0]
        free = ~fixed
        m = hess * (free[:, :, None] & free[:, None, :])
        np.einsum("bii->bi", m)[...] += fixed
        return np.linalg.solve(m, np.where(fixed, 0.0, -0.5 * grad)[..., None])[..., 0]

    def _line_search(self, ocp, x0, x_ref, u_prev, u, delta, f, lo, hi, with_jacobian):  # noqa: ANN001, ANN202
        """The first step length alone (usually the full step, which near the optimum always wins), then the
        others in one batch only for the problems it did not improve; with_jacobian: residuals and Jacobians
        come along (None otherwise)."""
        horizon_nu = (ocp.horizon, ocp.nu)

        def evaluate(x0, cand, x_ref, u_prev):  # noqa: ANN001, ANN202
            if with_jacobian:
                r, jac, sens = self._jacobian(ocp, x0, cand.reshape(-1, cand.shape[-1]), x_ref, u_prev)
            else:
                cand = cand.reshape(-1, *horizon_nu)
                r, jac, sens = ocp.residuals(ocp.rollout(x0, cand), cand, x_ref, u_prev), None, None
            return np.einsum("bm,bm->b", r, r), r, jac, sens

        cand = np.clip(u + self.alphas[0] * delta, lo, hi)
        best_c, best_r, best_jac, best_sens = evaluate(x0, cand, x_ref, u_prev)
        retry = np.flatnonzero(best_c >= f)
        if retry.size == 0 or self.alphas.size == 1:
            return best_c, cand, best_r, best_jac, best_sens
        k, m, alphas = self.alphas.size - 1, retry.size, self.alphas[1:]
        cands = np.clip(
            u[retry, None, :] + alphas[None, :, None] * delta[retry, None, :], lo[retry, None], hi[retry, None]
        )
        c, r_c, jac_c, sens_c = evaluate(
            np.repeat(x0[retry], k, 0), cands, np.repeat(x_ref[retry], k, 0), np.repeat(u_prev[retry], k, 0)
        )
        c = c.reshape(m, k)
        best = c.argmin(-1)
        pick = np.arange(m) * k + best
        c_best = c[np.arange(m), best]
        better = c_best < best_c[retry]
        rows, pick = retry[better], pick[better]
        best_c[rows], cand[rows], best_r[rows] = c_best[better], cands[better, best[better]], r_c[pick]
        if with_jacobian:
            best_jac[rows] = jac_c[pick]
            if best_sens is not None:
                best_sens[rows] = sens_c[pick]
        return best_c, cand, best_r, best_jac, best_sens


@dataclass
class LiftedGaussNewtonSolver(GaussNewtonSolver):
    """Gauss-Newton on the lifted (multiple-shooting) problem, condensed back to the inputs.

    The states at the start of each horizon step are extra unknowns: every iteration evaluates the
    network and its Jacobians at all H steps in one batched call instead of H sequential ones,
    condenses the linearised dynamics into a least-squares step on U (the defects ride along as
    offsets), and moves the states to the linearised prediction. At convergence the defects vanish,
    so the solution is that of the single-shooting problem; its cost comes from a final rollout.
    Falls back to single-shooting Gauss-Newton when it does not converge or ends worse than it began.
    """

    tol_defect: float = 1e-10  # converged also needs every state defect F(s_i, u_i) - s_{i+1} below this
    lifted_max_iter: int = 5  # lifted iterations before single shooting (max_iter more) takes over
    accepts_prior: ClassVar[bool] = False

    def _solve(self, ocp, x0, U0, x_ref, u_prev, low, high, prior):  # noqa: ANN001, ANN202
        """Lifted iterations on the numpy surrogate; single shooting when there is none or they fail."""
        if ocp.flow is None:
            return super()._solve(ocp, x0, U0, x_ref, u_prev, low, high, None)
        shape, (horizon, nx, nu) = U0.shape, (ocp.horizon, ocp.nx, ocp.nu)
        n = horizon * nu
        x0b, refb = x0.reshape(-1, nx), x_ref.reshape(-1, horizon, nx)
        upb = u_prev.reshape(-1, nu)
        U = np.clip(U0, low, high).reshape(-1, n)
        lo, hi = np.broadcast_to(low, shape).reshape(-1, n), np.broadcast_to(high, shape).reshape(-1, n)
        batch = U.shape[0]
        X = ocp.rollout(x0b, U.reshape(-1, horizon, nu))
        r0 = ocp.residuals(X, U.reshape(-1, horizon, nu), refb, upb)
        start_cost = np.einsum("bm,bm->b", r0, r0)
        nodes = np.empty((batch, horizon, nx))  # s_0 = x0 (fixed), s_1..s_{H-1} lifted
        nodes[:, 0] = x0b
        nodes[:, 1:] = X[:, :-1]
        running = np.ones(batch, dtype=bool)
        iterations = np.zeros(batch, dtype=np.int64)
        predictions = np.full((batch, 2), np.inf)  # the two previous predicted decreases, latest first
        for _ in range(self.lifted_max_iter):
            # all problems while all run (the batch-1 case), else the running rows only
            idx = slice(None) if running.all() else np.flatnonzero(running)
            rows, u = np.arange(batch)[idx], U[idx]
            pred, sens, defect = self._condense(ocp, nodes[idx], u)
            r, jac = ocp.least_squares(pred, sens, u, refb[idx], upb[idx])
            delta, pgrad_max, predicted = self._step(r, jac, u, lo[idx], hi[idx])
            f = np.einsum("bm,bm->b", r, r)
            small = (pgrad_max < self.tol_grad) | (predicted <= self.tol_cost * np.maximum(f, 1e-300))
            go = ~(small & (defect <= self.tol_defect))
            # this step is the last when what remains after it, extrapolated from the model's predicted
            # decreases, is negligible: the final rollout below then measures the cost reached
            last = go & (self._remaining(predicted, predictions[idx]) <= self.tol_gap * f)
            predictions[idx] = np.stack((predicted, predictions[idx, 0]), -1)
            iterations[rows[go]] += 1
            step = np.where(go[:, None], np.clip(u + delta, lo[idx], hi[idx]) - u, 0.0)
            U[idx] = u + step
            # the states move to the linearised prediction (within the defect tolerance for those that stop)
            nodes[rows, 1:] = pred[:, :-1] + (sens[:, :-1] @ step[:, None, :, None])[..., 0]
            running[rows[~go | last]] = False
            if not running.any():
                break
        U3 = U.reshape(-1, horizon, nu)
        cost = ocp.cost(x0b, U3, refb, upb)
        failed = running | ~np.isfinite(cost) | (cost > start_cost)
        if failed.any():  # rare: redo those problems by single shooting from the better of start and end
            rows = np.flatnonzero(failed)
            start = np.where(
                (cost[rows] < start_cost[rows])[:, None], U[rows], np.clip(U0, low, high).reshape(-1, n)[rows]
            )
            sub = super()._solve(
                ocp,
                x0b[rows],
                start.reshape(-1, horizon, nu),
                refb[rows],
                upb[rows],
                lo[rows].reshape(-1, horizon, nu),
                hi[rows].reshape(-1, horizon, nu),
                None,
            )
            U[rows], iterations[rows], cost[rows] = sub[0].reshape(-1, n), iterations[rows] + sub[1], sub[2]
            running[rows] = ~sub[3]
        return _result(shape, _project(U, lo, hi), iterations, cost, ~running, None)

    @staticmethod
    def _condense(ocp, nodes, U):  # noqa: ANN001, ANN205
        """One batched network call at all nodes, then the linearised predictions x_1..x_H, their
        sensitivities to U (chained along the horizon) and the largest defect per problem."""
        batch, horizon, nx = nodes.shape
        nu = ocp.nu
        y, a, b = ocp.flow.step_with_jacobian(nodes, U.reshape(batch, horizon, nu))
        pred = y.copy()
        sens = np.zeros((batch, horizon, nx, horizon * nu))
        for i in range(horizon):
            if i:
                offset = pred[:, i - 1] - nodes[:, i]  # the defect, carried through the linearisation
                pred[:, i] += (a[:, i] @ offset[..., None])[..., 0]
                np.matmul(a[:, i], sens[:, i - 1, :, : i * nu], out=sens[:, i, :, : i * nu])
            sens[:, i, :, i * nu : (i + 1) * nu] = b[:, i]
        defect = np.abs(y[:, :-1] - nodes[:, 1:]).reshape(batch, -1).max(-1, initial=0.0)
        return pred, sens, defect


SOLVERS = {
    "gauss_newton": GaussNewtonSolver,
    "lifted_gauss_newton": LiftedGaussNewtonSolver,
    "rmsprop": RMSpropSolver,
    "lbfgs": LBFGSSolver,
}


def make_solver(name: str, **options: object) -> Solver:
    """Solver by config name, with a clear error for unknown names or options."""
    if name not in SOLVERS:
        raise ValueError(f"unknown solver {name!r}; expected one of {sorted(SOLVERS)}")
    try:
        return SOLVERS[name](**options)
    except TypeError as e:
        raise ValueError(f"bad options for solver {name!r}: {e}") from e
