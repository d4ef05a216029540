"""The paper's solver: RMSprop on the inputs with autograd gradients, clamped to the box after every step."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor

from pinnmpc.controller.solvers.base import NO_WARM, NoWarm, Problem, SolveInfo, check_fields, cold_inputs


@dataclass
class RMSpropSolver:
    """Projected first-order descent: the paper's baseline, slow but needing nothing beyond autograd."""

    lr: float = 0.01
    """RMSprop learning rate."""
    max_iter: int = 1000
    """Iteration cap (the paper's 1000)."""
    tol: float = 1e-8
    """Stop when the summed cost changes less than this (the paper's 1e-8)."""
    array_api: ClassVar[str] = "torch"

    def __post_init__(self) -> None:
        check_fields(self)

    def solve(self, problem: Problem, U0: Tensor, warm: NoWarm = NO_WARM) -> tuple[Tensor, SolveInfo, NoWarm]:
        """Optimised inputs and statistics; no warm state, since the optimiser's moments start afresh each solve."""
        U = cold_inputs(self, U0, warm)
        ocp, x0, x_ref, u_prev = problem.ocp, problem.x0, problem.x_ref, problem.u_prev
        low, high = problem.low, problem.high
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
        return U, SolveInfo(torch.full(final.shape, it), final, converged), NO_WARM
