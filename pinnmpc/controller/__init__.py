"""NMPC on a surrogate: the OCP, its solvers and the receding-horizon controller."""

from pinnmpc.controller.nmpc import NMPC, StepStats
from pinnmpc.controller.ocp import HorizonOCP
from pinnmpc.controller.solvers import (
    NO_WARM,
    SOLVERS,
    GaussNewtonSolver,
    GaussNewtonWarm,
    LBFGSSolver,
    LiftedGaussNewtonSolver,
    LiftedWarm,
    NoWarm,
    Problem,
    RMSpropSolver,
    SolveInfo,
    make_solver,
)

__all__ = [
    "NMPC",
    "NO_WARM",
    "SOLVERS",
    "GaussNewtonSolver",
    "GaussNewtonWarm",
    "HorizonOCP",
    "LBFGSSolver",
    "LiftedGaussNewtonSolver",
    "LiftedWarm",
    "NoWarm",
    "Problem",
    "RMSpropSolver",
    "SolveInfo",
    "StepStats",
    "make_solver",
]
