"""Solvers for the batched box-constrained horizon OCP, one concern per module; make_solver picks one by name."""

from __future__ import annotations

from pinnmpc.controller.solvers.base import BOUND_TOL, SolveInfo, Solver, project
from pinnmpc.controller.solvers.first_order import LBFGSSolver, RMSpropSolver
from pinnmpc.controller.solvers.gauss_newton import GaussNewtonSolver
from pinnmpc.controller.solvers.lifted import LiftedGaussNewtonSolver

__all__ = [
    "BOUND_TOL",
    "SOLVERS",
    "GaussNewtonSolver",
    "LBFGSSolver",
    "LiftedGaussNewtonSolver",
    "RMSpropSolver",
    "SolveInfo",
    "Solver",
    "make_solver",
    "project",
]

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
