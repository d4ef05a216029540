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


def _result(shape: tuple[int, ...], U, iterations, cost, converged, warm):
    """A solve's outputs in the problems' own batch shape (warm: the next solve's prior, flat batch)."""
    lead = shape[:-2]
    return U.reshape(shape), iterations.reshape(lead), cost.reshape(lead), converged.reshape(lead), warm


@dataclass
class SolveInfo:
    """Per-problem solver statistics, batched like the problems."""

    iterations: Tensor  # (B,) int
    cost: Tensor  # (B,) float
    converged: Tensor  # (B,) bool
    sensitivities: np.ndarray | None = None  # (B, H, nx, H*nu) d x_i / d U near the solution, for the next solve
    states: np.ndarray | None = None  # (B, H, nx) the states x_1..x_H the solution reaches on the surrogate


class Solver(Protocol):
    """Minimise the OCP over U (B, H, nu) within [low, high], starting from U0.

    array_api names the array library the solver works in ("torch" or "numpy"): NMPC.make_step
    hands it arrays of that kind, so batch-1 solves pay no conversions. Solvers with accepts_prior
    take prior= (the last solve's SolveInfo field named by their prior_kind) as a warm start beyond U0.
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
        high: Tensor,
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

    def solve(self, ocp, x0, U0, x_ref, u_prev, low, high):
        """Projected first-order descent with autograd gradients."""
        U = U0.clone().requires_grad_(True)
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
        U = U.detach()
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

    def solve(self, ocp, x0, U0, x_ref, u_prev, low, high):
        """Quasi-Newton with strong Wolfe line search and clamping."""
        U = U0.clone().requires_grad_(True)
        opt = torch.optim.LBFGS([U], lr=1.0, max_iter=self.max_iter, line_search_fn="strong_wolfe")
        evals = [0]

        def closure() -> Tensor:
            opt.zero_grad()
            cost = ocp.cost(x0, U, x_ref, u_prev).sum()
            cost.backward()
            evals[0] += 1
            return cost

        with torch.no_grad():  # per problem the best feasible point so far: L-BFGS lowers the summed cost, and
            best_u = torch.maximum(torch.minimum(U0, high), low)  # a projection can undo a round's gain
            best = ocp.cost(x0, best_u, x_ref, u_prev)
        prev = float("inf")
        for _ in range(self.rounds):
            cost = float(opt.step(closure).detach())
            with torch.no_grad():
                U.copy_(torch.maximum(torch.minimum(U, high), low))
                reached = ocp.cost(x0, U, x_ref, u_prev)
                better = reached < best
                best_u[better], best = U[better], torch.where(better, reached, best)
            if abs(prev - cost) < self.tol * max(1.0, abs(cost)):
                break
            prev = cost
        return best_u, SolveInfo(torch.full(best.shape, evals[0]), best, torch.ones(best.shape, dtype=torch.bool))


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
    prior_kind: ClassVar[str] = "sensitivities"  # the SolveInfo field the next solve takes as prior

    def __post_init__(self) -> None:
        self.alphas = np.asarray(self.step_lengths, dtype=np.float64)
        if self.alphas.ndim != 1 or self.alphas.size == 0 or np.any(self.alphas <= 0):
            raise ValueError(f"step_lengths must be a non-empty list of positive numbers, got {self.step_lengths}")

    def solve(self, ocp, x0, U0, x_ref, u_prev, low, high, prior=None):
        """Accepts torch or numpy; returns the same kind.

        prior: the previous receding-horizon solve's SolveInfo field named by prior_kind, when U0 is its
        plan shifted by one step: a warm start beyond U0 (see the solver's class docstring).
        """
        as_torch = isinstance(U0, Tensor)
        args = [
            a.detach().numpy() if isinstance(a, Tensor) else np.asarray(a, dtype=np.float64)
            for a in (x0, U0, x_ref, u_prev, low, high)
        ]
        if prior is not None and not self._uses_prior(ocp):
            prior = None
        if prior is not None:
            prior = np.asarray(prior, dtype=np.float64)
            want = self._prior_shape(ocp, int(np.prod(U0.shape[:-2])))
            if prior.shape != want:
                raise ValueError(f"prior {self.prior_kind} must have shape {want}, got {prior.shape}")
        with np.errstate(divide="ignore", invalid="ignore"):  # ratios of decreases not formed yet are NaN
            U, iterations, cost, converged, warm = self._solve(ocp, *args, prior)
        lead = U.shape[:-2]
        kind = {self.prior_kind: None if warm is None else warm.reshape(*lead, *warm.shape[1:])}
        if as_torch:
            info = SolveInfo(torch.from_numpy(iterations), torch.from_numpy(cost), torch.from_numpy(converged), **kind)
            return torch.from_numpy(U), info
        return U, SolveInfo(iterations, cost, converged, **kind)

    def _uses_prior(self, ocp: HorizonOCP) -> bool:
        """Whether a prior can help here: the Jacobian warm start needs the numpy surrogate and H >= 2."""
        return self.reuse_jacobian and ocp.flow is not None and ocp.horizon >= 2

    @staticmethod
    def _prior_shape(ocp: HorizonOCP, batch: int) -> tuple[int, ...]:
        """Shape of the prior this solver takes: the sensitivities d x_i / d U."""
        return (batch, ocp.horizon, ocp.nx, ocp.horizon * ocp.nu)

    def _solve(self, ocp, x0, U0, x_ref, u_prev, low, high, prior):
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
        decreases = np.full((batch, 2), np.nan)  # the two previous decreases, latest first
        for k in range(self.max_iter):
            # views while every problem runs (the batch-1 case), copies of the running rows otherwise
            idx = slice(None) if running.all() else np.flatnonzero(running)
            u_i, f = U[idx], cost[idx].copy()  # f must survive the update of cost below
            delta, pgrad_max, predicted, _ = self._step(r[idx], jac[idx], u_i, lo[idx], hi[idx])
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

    def _jacobian(self, ocp, x0, U, x_ref, u_prev, prior=None):
        """Residuals, Jacobian and (numpy surrogates) the state sensitivities that a later solve may reuse."""
        if ocp.flow is not None and self.reuse_jacobian:
            return ocp.jacobian_rollout(x0, U, x_ref, u_prev, prior)
        r, jac = ocp.residuals_and_jacobian(x0, U.reshape(-1, ocp.horizon, ocp.nu), x_ref, u_prev)
        return r, jac, None

    def _remaining(self, decrease: np.ndarray, previous: np.ndarray, fast: np.ndarray | None = None) -> np.ndarray:
        """Cost decrease still to come, extrapolated geometrically from the last three decreases.

        Gauss-Newton converges at least linearly, so with rho the larger of the two latest ratios of
        successive decreases what remains is at most decrease * rho / (1 - rho); near a zero-residual
        optimum it converges quadratically and this overestimates. Two ratios, not one, because a step
        cut short by a bound gives one tiny decrease in an otherwise slow sequence, and after large first
        steps from a poor start the next ratio is small even where convergence is slow. Where fast (this
        step and the one before were full Newton steps of the model, neither cut by a bound) and the latest
        ratio is below fast_ratio, the latest alone counts: the superlinear phase of a nearly zero-residual
        problem, where the ratio before still carries the first, large steps.
        previous (B, 2) holds the two decreases before this one, latest first; NaN until taken (a NaN
        ratio extrapolates to infinity).
        """
        latest, before = decrease / previous[:, 0], previous[:, 0] / previous[:, 1]
        rho = np.maximum(latest, before)
        if fast is not None:
            rho = np.where(fast & (latest <= self.fast_ratio) & (before == before), latest, rho)
        return np.where(rho < 1.0, decrease * rho / (1.0 - rho), np.inf)

    def _step(self, r, jac, u, lo, hi):
        """Gauss-Newton step within the box for residuals r and their Jacobian: see _newton_step."""
        jt = jac.swapaxes(-1, -2)
        return self._newton_step(jt @ jac, 2.0 * np.matmul(jt, r[..., None])[..., 0], u, lo, hi)

    def _newton_step(self, jtj, grad, u, lo, hi):
        """Gauss-Newton step within the box, by a primal active set on the (convex) Gauss-Newton model
        1/2 d^T (2 J^T J) d + grad^T d.

        Variables at a bound with the gradient pointing out start fixed. From there the free variables
        move along the model's Newton direction until one of them meets a bound; that one is fixed and
        the path goes on, until a full Newton step stays inside (at most n segments, usually one).
        The model decreases along every segment. Returns the step, the projected gradient's max-norm,
        the cost decrease the model predicts for the step and whether a bound cut the Newton step short.
        """
        tol = BOUND_TOL * (hi - lo)  # "at a bound" up to rounding: steps aimed at a bound land within it
        fixed = ((u - lo <= tol) & (grad > 0)) | ((hi - u <= tol) & (grad < 0))
        pgrad_max = np.abs(np.where(fixed, 0.0, grad)).max(-1)
        hess = jtj.copy()
        diagonal = np.einsum("bii->bi", hess)  # a writable view
        diagonal += self.damping * np.maximum(diagonal.mean(-1, keepdims=True), 1e-30)
        delta = self._masked_solve(hess, grad, fixed)
        moved = u + delta
        cut = (~fixed & ((moved > hi) | (moved < lo))).any(-1)
        if cut.any():
            delta = self._active_set_path(hess, grad, fixed, u, lo, hi)
        # ||r||^2 - ||r + J delta||^2 = -(grad . delta + delta^T J^T J delta)
        predicted = -np.einsum("bi,bi->b", delta, grad + np.matmul(jtj, delta[..., None])[..., 0])
        return delta, pgrad_max, predicted, cut

    def _active_set_path(self, hess, grad, fixed, u, lo, hi):
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
    def _masked_solve(hess, grad, fixed):
        """Newton direction of the model 1/2 d^T (2 hess) d + grad^T d on the free variables (0 on the fixed)."""
        if not fixed.any():
            return np.linalg.solve(hess, -0.5 * grad[..., None])[..., 0]
        free = ~fixed
        m = hess * (free[:, :, None] & free[:, None, :])
        np.einsum("bii->bi", m)[...] += fixed
        return np.linalg.solve(m, np.where(fixed, 0.0, -0.5 * grad)[..., None])[..., 0]

    def _line_search(self, ocp, x0, x_ref, u_prev, u, delta, f, lo, hi, with_jacobian):
        """The first step length alone (usually the full step, which near the optimum always wins), then the
        others in one batch only for the problems it did not improve; with_jacobian: residuals and Jacobians
        come along (None otherwise)."""
        horizon_nu = (ocp.horizon, ocp.nu)

        def evaluate(x0, cand, x_ref, u_prev):
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
    condenses the linearised dynamics into a Gauss-Newton step on U (the defects ride along as
    offsets) and moves the states to the linearised prediction. At convergence the defects vanish,
    so the solution is that of the single-shooting problem. The states start from the last solve's
    predicted trajectory, one step on, when the controller hands it over as prior (a receding-horizon
    warm start that costs no rollout); otherwise from a rollout of U0. Falls back to single-shooting
    Gauss-Newton when it does not converge or ends worse than it began.
    """

    tol_defect: float = 1e-10  # converged also needs every state defect F(s_i, u_i) - s_{i+1} below this
    fast_ratio: float = 1e-3  # a full step whose predicted decrease fell below this x the one before: see _remaining
    lifted_max_iter: int = 5  # lifted iterations before single shooting (max_iter more) takes over
    tol_final_defect: float = 1e-8  # the cost reached is measured by a full rollout where a defect exceeds this
    accepts_prior: ClassVar[bool] = True
    prior_kind: ClassVar[str] = "states"

    def _solve(self, ocp, x0, U0, x_ref, u_prev, low, high, prior):
        """Lifted iterations on the numpy surrogate; single shooting when there is none or they fail."""
        if ocp.flow is None:
            return (*super()._solve(ocp, x0, U0, x_ref, u_prev, low, high, None)[:4], None)
        shape, (horizon, nx, nu) = U0.shape, (ocp.horizon, ocp.nx, ocp.nu)
        n = horizon * nu
        x0b, refb = x0.reshape(-1, nx), x_ref.reshape(-1, horizon, nx)
        upb = u_prev.reshape(-1, nu)
        U = np.clip(U0, low, high).reshape(-1, n)
        lo, hi = np.broadcast_to(low, shape).reshape(-1, n), np.broadcast_to(high, shape).reshape(-1, n)
        batch = U.shape[0]
        nodes = np.empty((batch, horizon, nx))  # s_0 = x0 (fixed), s_1..s_{H-1} lifted
        nodes[:, 0] = x0b
        if prior is not None:  # the last plan's states x_2..x_H are this plan's s_1..s_{H-1}
            nodes[:, 1:] = prior[:, 1:]
        else:
            nodes[:, 1:] = ocp.rollout(x0b, U.reshape(-1, horizon, nu))[:, :-1]
        start_cost = None  # the model's cost of U0 at the first linearisation
        running = np.ones(batch, dtype=bool)
        iterations = np.zeros(batch, dtype=np.int64)
        predictions = np.full((batch, 2), np.nan)  # the two previous predicted decreases, latest first
        was_cut = np.ones(batch, dtype=bool)  # whether a bound cut the previous step short (none taken yet)
        for _ in range(self.lifted_max_iter):
            # the whole batch every time (no row gathering: batch-1 solves are dominated by per-op overhead);
            # problems that stopped take no further steps, their states only settle onto the prediction
            pred, sens, defect, chain = self._linearise(ocp, nodes, U)
            f, jtj, grad = ocp.gauss_newton_model(pred, sens, U, refb, upb)
            if start_cost is None:
                start_cost = f
            delta, pgrad_max, predicted, cut = self._newton_step(jtj, grad, U, lo, hi)
            small = (pgrad_max < self.tol_grad) | (predicted <= self.tol_cost * f)
            go = running & ~(small & (defect <= self.tol_defect))
            # this step is the last when what remains after it, extrapolated from the model's predicted
            # decreases, is negligible: the cost reached is measured below
            last = self._remaining(predicted, predictions, ~(cut | was_cut)) <= self.tol_gap * f
            predictions[:, 1] = predictions[:, 0]
            predictions[:, 0] = predicted
            was_cut = cut
            iterations += go
            step = np.where(go[:, None], np.clip(U + delta, lo, hi) - U, 0.0)
            U += step
            # the states move to the linearised prediction (within the defect tolerance for those that stop)
            moved = pred.reshape(batch, -1) + (sens @ step[..., None])[..., 0]
            nodes[:, 1:] = moved.reshape(batch, horizon, nx)[:, :-1]
            running &= go & ~last
            if not running.any():
                break
        U3 = U.reshape(-1, horizon, nu)
        X = self._reached(ocp, x0b, nodes, U3, chain)
        cost = (ocp.residuals(X, U3, refb, upb) ** 2).sum(-1)
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
            X[rows] = ocp.rollout(x0b[rows], U[rows].reshape(-1, horizon, nu))
        return _result(shape, _project(U, lo, hi), iterations, cost, ~running, X)

    def _uses_prior(self, ocp: HorizonOCP) -> bool:
        """The states warm start needs the numpy surrogate."""
        return ocp.flow is not None

    @staticmethod
    def _prior_shape(ocp: HorizonOCP, batch: int) -> tuple[int, ...]:
        """Shape of the prior this solver takes: the last plan's states x_1..x_H."""
        return (batch, ocp.horizon, ocp.nx)

    @staticmethod
    def _linearise(ocp, nodes, U):
        """One batched network call at all nodes, then the linearised predictions x_1..x_H (B, H, nx), their
        sensitivities to U (B, H*nx, H*nu), the largest defect per problem and the chain matrix.

        The chain x_i = y_i + A_i (x_{i-1} - s_i) over the horizon is one block-triangular solve with the
        chain matrix I - L (L: the A_i on the block subdiagonal): for the predictions and all H*nu input
        directions at once.
        """
        batch, horizon, nx = nodes.shape
        nu = ocp.nu
        y, a, b = ocp.step_with_jacobian(nodes, U.reshape(batch, horizon, nu))
        chain = _chain_matrix(a)
        rhs = np.zeros((batch, horizon, nx, horizon * nu + 1))
        blocks = rhs[..., :-1].reshape(batch, horizon, nx, horizon, nu)
        diag = np.arange(horizon)
        blocks[:, diag, :, diag, :] = b.swapaxes(0, 1)  # x_i depends directly on u_i only through B_i
        rhs[..., -1] = y
        rhs[:, 1:, :, -1] -= (a[:, 1:] @ nodes[:, 1:, :, None])[..., 0]
        sol = np.linalg.solve(chain, rhs.reshape(batch, horizon * nx, -1))
        defect = np.abs(y[:, :-1] - nodes[:, 1:]).reshape(batch, -1).max(-1, initial=0.0)
        return sol[..., -1].reshape(batch, horizon, nx), sol[..., :-1], defect, chain

    def _reached(self, ocp, x0, nodes, U, chain):
        """The states U reaches from x0 (B, H, nx): one batched network call at the final nodes, their defects
        carried through the last linearisation (x_i - y_i = A_i (x_{i-1} - y_{i-1} + gap_{i-1}), exact to
        second order in the defects, which are tiny at convergence); a full rollout where one is larger
        than tol_final_defect."""
        batch, horizon, nx = nodes.shape
        y = ocp.step(nodes, U)
        gap = np.zeros((batch, horizon, nx))  # gap_i = F(s_i, u_i) - s_{i+1}: the defect at the end of step i
        gap[:, :-1] = y[:, :-1] - nodes[:, 1:]
        X = y + np.linalg.solve(chain, gap.reshape(batch, -1, 1)).reshape(batch, horizon, nx) - gap
        far = np.flatnonzero(np.abs(gap).reshape(batch, -1).max(-1) > self.tol_final_defect)
        if far.size:
            X[far] = ocp.rollout(x0[far], U[far])
        return X


def _chain_matrix(a: np.ndarray) -> np.ndarray:
    """I - L for step Jacobians a (B, H, nx, nx): L holds A_1..A_{H-1} on the block subdiagonal."""
    batch, horizon, nx, _ = a.shape
    chain = np.zeros((batch, horizon, nx, horizon, nx))
    diag, sub = np.arange(horizon), np.arange(1, horizon)
    chain[:, diag, :, diag, :] = np.eye(nx)
    chain[:, sub, :, sub - 1, :] = -a[:, 1:].swapaxes(0, 1)
    return chain.reshape(batch, horizon * nx, horizon * nx)


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
