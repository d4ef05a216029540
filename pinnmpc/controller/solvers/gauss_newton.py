"""Projected Gauss-Newton on the horizon OCP's least-squares structure (single shooting), batched, in numpy.

The iteration (Jacobians, line search, stopping tests) lives here; the step within the box is
pinnmpc.controller.box_step's, the rollouts and sensitivities pinnmpc.controller.shooting's (via HorizonOCP).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch
from torch import Tensor

from pinnmpc.controller.array_backend import Array, Nd
from pinnmpc.controller.box_step import newton_step, normal_equations
from pinnmpc.controller.ocp import HorizonOCP
from pinnmpc.controller.solvers.base import (
    NO_WARM,
    NoWarm,
    Problem,
    SolveInfo,
    SolveResult,
    check_fields,
    project,
    result,
    wrong_warm,
)


@dataclass(frozen=True, eq=False)
class GaussNewtonWarm:
    """Gauss-Newton's receding-horizon warm start: the last solution's state sensitivities d x_i / d U.

    Shifted by one step they are the next problem's Jacobian but for its last step, which saves H - 1
    of the H network Jacobians of the first iteration.
    """

    sensitivities: np.ndarray  # (B, H, nx, H*nu)


@dataclass
class GaussNewtonSolver:
    """Projected Gauss-Newton / Levenberg-Marquardt on the least-squares structure, batched, in numpy.

    Jacobians come from forward-mode tangents through the network; bounds are handled
    by an active set (variables at a bound whose gradient points outward are frozen)
    and projection; the step length is the best of a few candidates evaluated in one
    batched rollout. numpy, because batch-1 solves are dominated by per-op overhead.
    """

    max_iter: int = 30
    """Iteration cap (`controller.solvers.gauss_newton.max_iter`)."""
    tol_grad: float = 1e-9
    """Converged when the projected gradient's max-norm is below this."""
    tol_cost: float = 1e-10
    """... or when the relative cost decrease predicted (or achieved) by a step is below this."""
    tol_gap: float = 1e-8
    """... or when the decrease still to come, extrapolated from the last two steps, is below this x the cost."""
    damping: float = 1e-9
    """Levenberg-Marquardt damping, relative to the mean diagonal of J^T J."""
    step_lengths: tuple[float, ...] = (1.0, 0.5, 0.25, 0.1, 0.01)
    """Line search: the first tried alone, then the rest at once in one batched rollout."""
    reuse_jacobian: bool = True
    """Receding horizon: the first step reuses the last solve's sensitivities, shifted by one step."""
    array_api: ClassVar[str] = "numpy"  # also accepts torch tensors (and then returns them)
    warm_type: ClassVar[type] = GaussNewtonWarm  # the warm state this solver hands on and takes back
    warm_field: ClassVar[str] = "sensitivities"  # ... and its array

    def __post_init__(self) -> None:
        check_fields(self)
        self.alphas = np.asarray(self.step_lengths, dtype=np.float64)
        if self.alphas.ndim != 1 or self.alphas.size == 0 or np.any(self.alphas <= 0):
            raise ValueError(
                f"{type(self).__name__}.step_lengths={list(self.step_lengths)}; expected a non-empty list of "
                "positive numbers"
            )

    def solve(
        self, problem: Problem, U0: Array, warm: GaussNewtonWarm | NoWarm = NO_WARM
    ) -> tuple[Array, SolveInfo, GaussNewtonWarm | NoWarm]:
        """Optimised inputs, statistics and the sensitivities for the next solve; torch in, torch out.

        warm: what this solver returned for the previous receding-horizon problem, whose plan shifted by
        one step is U0: a Jacobian warm start beyond U0 (see the class docstring); NO_WARM: none.
        """
        as_torch = isinstance(U0, Tensor)
        args = [
            a.detach().numpy() if isinstance(a, Tensor) else np.asarray(a, dtype=np.float64)
            for a in (problem.x0, U0, problem.x_ref, problem.u_prev, problem.low, problem.high)
        ]
        lead = tuple(U0.shape[:-2])
        prior = self._warm_array(warm, problem.ocp, lead)
        with np.errstate(divide="ignore", invalid="ignore"):  # ratios of decreases not formed yet are NaN
            U, iterations, cost, converged, out = self._solve(problem.ocp, *args, prior)
        out = None if out is None else out.reshape(*lead, *out.shape[1:])
        next_warm, states = self._next_warm(out)
        if as_torch:
            info = SolveInfo(torch.from_numpy(iterations), torch.from_numpy(cost), torch.from_numpy(converged), states)
            return torch.from_numpy(U), info, next_warm
        return U, SolveInfo(iterations, cost, converged, states), next_warm

    def _warm_array(self, warm: object, ocp: HorizonOCP, lead: tuple[int, ...]) -> np.ndarray | None:
        """The array of this solver's warm state (warm_field of a warm_type) as a flat batch, checked against this
        problem (None: unused)."""
        if isinstance(warm, NoWarm):
            return None
        if not isinstance(warm, self.warm_type):
            raise wrong_warm(self, warm, f"{self.warm_type.__name__} or NoWarm")
        return self._checked(getattr(warm, self.warm_field), self.warm_field, ocp, lead)

    def _checked(self, array: np.ndarray, name: str, ocp: HorizonOCP, lead: tuple[int, ...]) -> np.ndarray | None:
        """A warm-start array of the expected shape as a flat batch; None where it cannot help this problem."""
        if not self._uses_warm(ocp):
            return None
        array = np.asarray(array, dtype=np.float64)
        want = (*lead, *self._warm_shape(ocp))
        if array.shape != want:
            raise ValueError(f"warm {name} must have shape {want}, got {array.shape}")
        return array.reshape(-1, *array.shape[len(lead) :])

    @staticmethod
    def _next_warm(out: np.ndarray | None) -> tuple[GaussNewtonWarm | NoWarm, None]:
        """The next solve's warm state from the last sensitivities (none without the numpy surrogate); no states."""
        return (NO_WARM if out is None else GaussNewtonWarm(out)), None

    def _uses_warm(self, ocp: HorizonOCP) -> bool:
        """Whether a warm start can help here: the Jacobian warm start needs the numpy surrogate and H >= 2."""
        return self.reuse_jacobian and ocp.flow is not None and ocp.horizon >= 2

    @staticmethod
    def _warm_shape(ocp: HorizonOCP) -> tuple[int, ...]:
        """Shape per problem of the warm array this solver takes: the sensitivities d x_i / d U."""
        return (ocp.horizon, ocp.nx, ocp.horizon * ocp.nu)

    def _solve(
        self,
        ocp: HorizonOCP,
        x0: Nd,
        U0: Nd,
        x_ref: Nd,
        u_prev: Nd,
        low: Nd,
        high: Nd,
        prior: Nd | None,
        max_iter: int | None = None,
    ) -> SolveResult:
        """Iterate until every problem has converged or max_iter (the setting, unless a caller caps it) is reached.

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
        U = np.minimum(np.maximum(U0, low), high).reshape(-1, n)  # np.clip's values, without its Python wrapper
        lo, hi = (np.zeros(shape) + low).reshape(-1, n), (np.zeros(shape) + high).reshape(-1, n)
        batch = U.shape[0]
        r, jac, sens = self._jacobian(ocp, x0b, U, refb, upb, prior)
        cost = np.einsum("bm,bm->b", r, r)
        running = np.ones(batch, dtype=bool)
        iterations = np.zeros(batch, dtype=np.int64)
        decreases = np.full((batch, 2), np.nan)  # the two previous decreases, latest first
        for k in range(self.max_iter if max_iter is None else max_iter):
            # views while every problem runs (the batch-1 case), copies of the running rows otherwise
            idx = slice(None) if running.all() else np.flatnonzero(running)
            u_i, f = U[idx], cost[idx].copy()  # f must survive the update of cost below
            jtj, grad = normal_equations(r[idx], jac[idx])
            delta, pgrad_max, predicted, _ = newton_step(jtj, grad, u_i, lo[idx], hi[idx], self.damping)
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
        return result(shape, project(U, lo, hi), iterations, cost, ~running, sens)

    def _jacobian(
        self,
        ocp: HorizonOCP,
        x0: np.ndarray,
        U: np.ndarray,
        x_ref: np.ndarray,
        u_prev: np.ndarray,
        prior: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
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
        problem, where the ratio before still carries the first, large steps. That holds from the second step on
        (one ratio taken): a warm-started receding-horizon solve is in that phase from its first step, and then
        stops after two linearisations instead of confirming with a third; cold starts rarely pass the fast test
        there (docs/design.md, NMPC).
        previous (B, 2) holds the two decreases before this one, latest first; NaN until taken (a NaN
        ratio extrapolates to infinity, outside the fast case).
        """
        latest, before = decrease / previous[:, 0], previous[:, 0] / previous[:, 1]
        rho = np.maximum(latest, before)
        if fast is not None:
            rho = np.where(fast & (latest <= self.fast_ratio), latest, rho)
        return np.where(rho < 1.0, decrease * rho / (1.0 - rho), np.inf)

    def _line_search(
        self,
        ocp: HorizonOCP,
        x0: np.ndarray,
        x_ref: np.ndarray,
        u_prev: np.ndarray,
        u: np.ndarray,
        delta: np.ndarray,
        f: np.ndarray,
        lo: np.ndarray,
        hi: np.ndarray,
        with_jacobian: bool,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
        """The first step length alone (usually the full step, which near the optimum always wins), then the
        others in one batch only for the problems it did not improve; with_jacobian: residuals and Jacobians
        come along (None otherwise)."""
        horizon_nu = (ocp.horizon, ocp.nu)

        def evaluate(
            x0: np.ndarray, cand: np.ndarray, x_ref: np.ndarray, u_prev: np.ndarray
        ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
            """Costs, residuals and (with_jacobian) Jacobians and sensitivities of candidate inputs."""
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
