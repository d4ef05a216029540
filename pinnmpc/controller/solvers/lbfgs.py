"""torch.optim.LBFGS on the inputs, projected onto the box between rounds."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor

from pinnmpc.controller.solvers.base import NO_WARM, NoWarm, Problem, SolveInfo, check_fields, cold_inputs


@dataclass
class LBFGSSolver:
    """Quasi-Newton with strong Wolfe line search: a generic reference that needs only autograd gradients."""

    max_iter: int = 20
    """L-BFGS iterations per projection round."""
    rounds: int = 5
    """Projection rounds."""
    tol: float = 1e-12
    """Stop when a round changes the summed cost relatively less than this."""
    array_api: ClassVar[str] = "torch"

    def __post_init__(self) -> None:
        check_fields(self)

    def solve(self, problem: Problem, U0: Tensor, warm: NoWarm = NO_WARM) -> tuple[Tensor, SolveInfo, NoWarm]:
        """Optimised inputs and statistics; no warm state, since the curvature pairs belong to the last problem."""
        U = cold_inputs(self, U0, warm)
        ocp, x0, x_ref, u_prev = problem.ocp, problem.x0, problem.x_ref, problem.u_prev
        low, high = problem.low, problem.high
        opt = torch.optim.LBFGS([U], lr=1.0, max_iter=self.max_iter, line_search_fn="strong_wolfe")
        evals = [0]

        def closure() -> Tensor:
            opt.zero_grad()
            # the cost at U held inside the box: a line search's trial far outside it drove the arm's states (and its
            # mass matrix) to non-finite values; a bound's input gets no gradient past it, the round's projection
            # brings it back
            cost = ocp.cost(x0, torch.maximum(torch.minimum(U, high), low), x_ref, u_prev).sum()
            cost.backward()
            evals[0] += 1
            return cost

        with torch.no_grad():  # per problem the best feasible point so far: L-BFGS lowers the summed cost, and
            best_u = torch.maximum(torch.minimum(U0, high), low)  # a projection can undo a round's gain
            best = ocp.cost(x0, best_u, x_ref, u_prev)
        prev, settled = float("inf"), False
        for _ in range(self.rounds):
            cost = float(opt.step(closure).detach())
            with torch.no_grad():
                U.copy_(torch.maximum(torch.minimum(U, high), low))
                reached = ocp.cost(x0, U, x_ref, u_prev)
                better = reached < best
                best_u[better], best = U[better], torch.where(better, reached, best)
            if abs(prev - cost) < self.tol * max(1.0, abs(cost)):
                settled = True
                break
            prev = cost
        # the rounds share one summed cost, so the batch settles (or runs out of rounds) as a whole
        converged = torch.full(best.shape, settled, dtype=torch.bool)
        return best_u, SolveInfo(torch.full(best.shape, evals[0]), best, converged), NO_WARM
