"""Solvers for the batched box-constrained horizon OCP: the paper's RMSprop, L-BFGS, and a fast Gauss-Newton."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

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
            if abs(prev - float(cost)) < self.tol:
                break
            prev = float(cost)
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
            cost = float(opt.step(closure))
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
    """Projected Gauss-Newton / Levenberg-Marquardt on the least-squares structure, batched.

    Jacobians come from forward-mode tangents through the network; bounds are handled
    by an active set (variables at a bound whose gradient points outward are frozen)
    and projection; the step length is picked from a few candidates evaluated in one
    batched rollout.
    """

    max_iter: int = 30  # iteration cap
    tol_grad: float = 1e-9  # converged when the projected gradient's max-norm is below this
    tol_cost: float = 1e-12  # ... or the relative cost decrease of an iteration is below this
    damping: float = 1e-9  # Levenberg-Marquardt damping, relative to the mean diagonal of J^T J
    step_lengths: tuple[float, ...] = (1.0, 0.5, 0.25, 0.1, 0.01)  # candidate step lengths per iteration

    def solve(self, ocp, x0, U0, x_ref, u_prev, low, high):  # noqa: ANN001, ANN201, N803, C901
        """Iterate until every problem has converged or max_iter is reached."""
        shape = U0.shape
        n = shape[-1] * shape[-2]
        U = torch.maximum(torch.minimum(U0, high), low).reshape(-1, n)  # noqa: N806
        lo, hi = low.expand(shape).reshape(-1, n), high.expand(shape).reshape(-1, n)
        x0b, refb, upb = (
            x0.reshape(-1, x0.shape[-1]),
            x_ref.reshape(-1, *x_ref.shape[-2:]),
            u_prev.reshape(-1, shape[-1]),
        )
        batch = U.shape[0]
        active_problems = torch.ones(batch, dtype=torch.bool)
        iterations = torch.zeros(batch, dtype=torch.long)
        alphas = torch.tensor(self.step_lengths, dtype=U.dtype)
        eye = torch.eye(n, dtype=U.dtype)
        cost = torch.zeros(batch, dtype=U.dtype)
        with torch.no_grad():
            for _ in range(self.max_iter):
                idx = active_problems.nonzero().squeeze(-1)
                if idx.numel() == 0:
                    break
                u_i = U[idx]
                r, jac = ocp.residuals_and_jacobian(x0b[idx], u_i.reshape(-1, *shape[-2:]), refb[idx], upb[idx])
                f = r.square().sum(-1)
                cost[idx] = f
                grad = 2 * (jac.transpose(-1, -2) @ r.unsqueeze(-1)).squeeze(-1)
                bound = ((u_i <= lo[idx]) & (grad > 0)) | ((u_i >= hi[idx]) & (grad < 0))
                pgrad = torch.where(bound, 0.0, grad)
                done = pgrad.abs().amax(-1) < self.tol_grad
                free = (~bound).to(U.dtype)
                jtj = jac.transpose(-1, -2) @ jac
                mu = self.damping * jtj.diagonal(dim1=-2, dim2=-1).mean(-1).clamp_min(1e-30)
                hess = jtj * free.unsqueeze(-1) * free.unsqueeze(-2) + torch.diag_embed(1 - free)
                hess = hess + mu[:, None, None] * eye
                delta = torch.linalg.solve(hess, (-pgrad / 2).unsqueeze(-1)).squeeze(-1)
                cand = u_i.unsqueeze(1) + alphas[None, :, None] * delta.unsqueeze(1)
                cand = torch.maximum(torch.minimum(cand, hi[idx].unsqueeze(1)), lo[idx].unsqueeze(1))
                k = len(self.step_lengths)
                c = ocp.cost(
                    x0b[idx].repeat_interleave(k, 0),
                    cand.reshape(-1, *shape[-2:]),
                    refb[idx].repeat_interleave(k, 0),
                    upb[idx].repeat_interleave(k, 0),
                ).reshape(-1, k)
                best_c, best = c.min(-1)
                improved = best_c < f
                step = improved & ~done
                U[idx[step]] = cand[step, best[step]]
                cost[idx[step]] = best_c[step]
                iterations[idx] += 1
                small = (f - best_c) <= self.tol_cost * f.clamp_min(1e-300)
                active_problems[idx[done | ~improved | small]] = False
        converged = ~active_problems
        return U.reshape(shape), SolveInfo(iterations, cost.reshape(shape[:-2]), converged.reshape(shape[:-2]))


SOLVERS = {"gauss_newton": GaussNewtonSolver, "rmsprop": RMSpropSolver, "lbfgs": LBFGSSolver}


def make_solver(name: str, **options: object) -> Solver:
    """Solver by config name, with a clear error for unknown names or options."""
    if name not in SOLVERS:
        raise ValueError(f"unknown solver {name!r}; expected one of {sorted(SOLVERS)}")
    try:
        return SOLVERS[name](**options)
    except TypeError as e:
        raise ValueError(f"bad options for solver {name!r}: {e}") from e
