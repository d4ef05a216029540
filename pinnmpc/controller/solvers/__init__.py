"""Solvers for the batched box-constrained horizon OCP, one per module; make_solver picks one by name.

Each is a settings dataclass (the structured config of controller.solvers.<name>: register_configs) with
solve(problem, U0, warm) -> (U, info, next_warm), where warm is the solver's own frozen warm-start state
(NO_WARM: a cold start) that the caller hands back on the next receding-horizon solve.
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
    "register_configs",
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
    except ValueError as e:  # a value its __post_init__ refused
        raise ValueError(f"controller.solvers.{name}: {e}") from None


def register_configs() -> None:
    """Each solver's dataclass as the structured config of `controller.solvers.<name>` (the defaults list of
    conf/controller/nmpc.yaml): its fields, types and defaults are the settings, its field docstrings their
    documentation. The commands call this before Hydra composes; call it before hydra.compose of your own."""
    from hydra.core.config_store import ConfigStore

    store = ConfigStore.instance()
    for name, cls in SOLVERS.items():
        store.store(group="controller/solvers", name=name, node=cls)
