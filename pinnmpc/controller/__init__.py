"""NMPC on a surrogate: the OCP, its solvers and the receding-horizon controller."""

from pinnmpc.controller.nmpc import NMPC, StepStats
from pinnmpc.controller.ocp import HorizonOCP
from pinnmpc.controller.solvers import (
    SOLVERS,
    GaussNewtonSolver,
    LBFGSSolver,
    LiftedGaussNewtonSolver,
    RMSpropSolver,
    make_solver,
)

__all__ = [
    "NMPC",
    "SOLVERS",
    "GaussNewtonSolver",
    "HorizonOCP",
    "LBFGSSolver",
    "LiftedGaussNewtonSolver",
    "RMSpropSolver",
    "StepStats",
    "make_solver",
]
