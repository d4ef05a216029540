"""Solvers for the batched box-constrained horizon OCP, one per module; make_solver picks one by name.

Each is a settings dataclass with solve(problem, U0, warm) -> (U, info, next_warm), where warm is the
solver's own frozen warm-start state (NO_WARM: a cold start) that the caller hands back on the next
receding-horizon solve.
"""

from __future__ import annotations

from pinnmpc.controller.solvers.base import BOUND_TOL, NO_WARM, NoWarm, Problem, SolveInfo, Solver, project
from pinnmpc.controller.solvers.gauss_newton import GaussNewtonSolver, GaussNewtonWarm
from pinnmpc.controller.solvers.lbfgs import LBFGSSolver
from pinnmpc.controller.solvers.lifted import LiftedGaussNewtonSolver, LiftedWarm
from pinnmpc.controller.solvers.rmsprop import RMSpropSolver

__all__ = [
    "BOUND_TOL",
    "NO_WARM",
    "SOLVERS",
    "GaussNewtonSolver",
    "GaussNewtonWarm",
    "LBFGSSolver",
    "LiftedGaussNewtonSolver",
    "LiftedWarm",
    "NoWarm",
    "Problem",
    "RMSpropSolver",
    "SolveInfo",
    "Solver",
    "make_solver",
    "project",
]

SOLVERS: dict[str, type[Solver]] = {
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
