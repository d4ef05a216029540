"""The autograd solvers: the paper's RMSprop, and L-BFGS projected between rounds."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor

from pinnmpc.controller.solvers.base import SolveInfo


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
