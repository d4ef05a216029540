"""Solvers for the batched box-constrained horizon OCP: the paper's RMSprop, L-BFGS, and a fast Gauss-Newton."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch
from torch import Tensor

from pinnmpc.controller.ocp import HorizonOCP


@dataclass
class SolveInfo:
    """Per-problem solver statistics, batched like the problems."""

    iterations: Tensor  # (B,) int
    cost: Tensor  # (B,) float
    converged: Tensor  # (B,) bool


class Solver(Protocol):
    """Minimise the OCP over U (B, H, nu) within [low, high], starting from U0."""

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
    damping: float = 1e-9  # Levenberg-Marquardt damping, relative to the mean diagonal of J^T J
    step_lengths: tuple[float, ...] = (1.0, 0.5, 0.25, 0.1, 0.01)  # tried first alone, then the rest at once

    def __post_init__(self) -> None:
        self.alphas = np.asarray(self.step_lengths, dtype=np.float64)
        if self.alphas.ndim != 1 or self.alphas.size == 0 or np.any(self.alphas <= 0):
            raise ValueError(f"step_lengths must be a non-empty list of positive numbers, got {self.step_lengths}")

    def solve(self, ocp, x0, U0, x_ref, u_prev, low, high):  # noqa: ANN001, ANN201
        """Accepts torch or numpy; returns the same kind."""
        as_torch = isinstance(U0, Tensor)
        args = [
            a.detach().numpy() if isinstance(a, Tensor) else np.asarray(a, dtype=np.float64)
            for a in (x0, U0, x_ref, u_prev, low, high)
        ]
        U, iterations, cost, converged = self._solve(ocp, *args)
        if as_torch:
            return torch.from_numpy(U), SolveInfo(
                torch.from_numpy(iterations), torch.from_numpy(cost), torch.from_numpy(converged)
            )
        return U, SolveInfo(iterations, cost, converged)

    def _solve(self, ocp, x0, U0, x_ref, u_prev, low, high):  # noqa: ANN001, ANN202
        """Iterate until every problem has converged or max_iter is reached.

        Residuals and Jacobians are evaluated at the candidate step lengths (see _line_search),
        so the accepted candidate's Jacobian is already there for the next iteration: usually
        one batch-1 rollout per iteration. A problem stops when the Gauss-Newton model predicts a relative
        decrease below tol_cost (no rollout needed to find that out), when its projected
        gradient vanishes, or when no candidate improves.
        """
        shape, horizon_nu = U0.shape, U0.shape[-2:]
        n = shape[-1] * shape[-2]
        x0b, refb = x0.reshape(-1, x0.shape[-1]), x_ref.reshape(-1, *x_ref.shape[-2:])
        upb = u_prev.reshape(-1, shape[-1])
        U = np.clip(U0, low, high).reshape(-1, n)
        lo, hi = np.broadcast_to(low, shape).reshape(-1, n), np.broadcast_to(high, shape).reshape(-1, n)
        batch = U.shape[0]
        r, jac = ocp.residuals_and_jacobian(x0b, U.reshape(-1, *horizon_nu), refb, upb)
        cost = (r * r).sum(-1)
        running = np.ones(batch, dtype=bool)
        iterations = np.zeros(batch, dtype=np.int64)
        eye = np.eye(n)
        for _ in range(self.max_iter):
            idx = np.flatnonzero(running)
            if idx.size == 0:
                break
            u_i, r_i, jac_i, f = U[idx], r[idx], jac[idx], cost[idx]
            jt = np.swapaxes(jac_i, -1, -2)
            grad = 2.0 * (jt @ r_i[..., None])[..., 0]
            bound = ((u_i <= lo[idx]) & (grad > 0)) | ((u_i >= hi[idx]) & (grad < 0))
            pgrad = np.where(bound, 0.0, grad)
            free = (~bound).astype(np.float64)
            jtj = jt @ jac_i
            mu = self.damping * np.maximum(np.diagonal(jtj, 0, -2, -1).mean(-1), 1e-30)
            hess = jtj * free[:, :, None] * free[:, None, :] + (1.0 - free)[:, :, None] * eye + mu[:, None, None] * eye
            delta = np.linalg.solve(hess, -0.5 * pgrad[..., None])[..., 0]
            predicted = -0.5 * (pgrad * delta).sum(-1)  # decrease the Gauss-Newton model expects
            done = (np.abs(pgrad).max(-1) < self.tol_grad) | (predicted <= self.tol_cost * np.maximum(f, 1e-300))
            running[idx[done]] = False
            go = ~done
            if not go.any():
                break
            idx, u_i, f, delta = idx[go], u_i[go], f[go], delta[go]
            best_c, new_u, new_r, new_jac = self._line_search(
                ocp, x0b[idx], refb[idx], upb[idx], u_i, delta, f, lo[idx], hi[idx]
            )
            improved = best_c < f
            acc = idx[improved]
            U[acc], r[acc], jac[acc], cost[acc] = new_u[improved], new_r[improved], new_jac[improved], best_c[improved]
            iterations[idx] += 1
            small = (f - best_c) <= self.tol_cost * np.maximum(f, 1e-300)
            running[idx[~improved | small]] = False
        return (
            U.reshape(shape),
            iterations.reshape(shape[:-2]),
            cost.reshape(shape[:-2]),
            (~running).reshape(shape[:-2]),
        )

    def _line_search(self, ocp, x0, x_ref, u_prev, u, delta, f, lo, hi):  # noqa: ANN001, ANN202
        """The first step length alone (usually the full step, which near the optimum always wins), then the
        others in one batch only for the problems it did not improve; residuals and Jacobians come along."""
        horizon_nu = (ocp.horizon, ocp.nu)

        def evaluate(rows: np.ndarray, alphas: np.ndarray) -> tuple[np.ndarray, ...]:
            k, m = alphas.size, rows.size
            cand = np.clip(
                u[rows, None, :] + alphas[None, :, None] * delta[rows, None, :], lo[rows, None], hi[rows, None]
            )
            r_c, jac_c = ocp.residuals_and_jacobian(
                np.repeat(x0[rows], k, 0),
                cand.reshape(m * k, *horizon_nu),
                np.repeat(x_ref[rows], k, 0),
                np.repeat(u_prev[rows], k, 0),
            )
            c = (r_c * r_c).sum(-1).reshape(m, k)
            best = c.argmin(-1)
            pick = np.arange(m) * k + best
            return c[np.arange(m), best], cand[np.arange(m), best], r_c[pick], jac_c[pick]

        everyone = np.arange(u.shape[0])
        best_c, best_u, best_r, best_jac = evaluate(everyone, self.alphas[:1])
        retry = everyone[best_c >= f]
        if retry.size and self.alphas.size > 1:
            c, cu, cr, cj = evaluate(retry, self.alphas[1:])
            better = c < best_c[retry]
            rows = retry[better]
            best_c[rows], best_u[rows], best_r[rows], best_jac[rows] = c[better], cu[better], cr[better], cj[better]
        return best_c, best_u, best_r, best_jac


SOLVERS = {"gauss_newton": GaussNewtonSolver, "rmsprop": RMSpropSolver, "lbfgs": LBFGSSolver}


def make_solver(name: str, **options: object) -> Solver:
    """Solver by config name, with a clear error for unknown names or options."""
    if name not in SOLVERS:
        raise ValueError(f"unknown solver {name!r}; expected one of {sorted(SOLVERS)}")
    try:
        return SOLVERS[name](**options)
    except TypeError as e:
        raise ValueError(f"bad options for solver {name!r}: {e}") from e
