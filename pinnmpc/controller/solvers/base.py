"""What every OCP solver shares: the problem, the result, the cold warm state, the protocol, box projection.

A solver is a settings dataclass with one method, solve(problem, U0, warm) -> (U, info, next_warm): the
warm state is each solver's own frozen dataclass (NoWarm for none), so what carries over from one
receding-horizon solve to the next is explicit and typed instead of probed for on a shared result.
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from torch import Tensor

from pinnmpc.controller.array_backend import Array
from pinnmpc.controller.box_step import BOUND_TOL
from pinnmpc.controller.ocp import HorizonOCP
from pinnmpc.util.checks import boolean, real, whole

__all__ = ["BOUND_TOL", "NO_WARM", "NoWarm", "Problem", "SolveInfo", "Solver", "project", "result", "wrong_warm"]


def project(u: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Clip to the box and put values within rounding of a bound exactly on it (the answer a user sees)."""
    tol = BOUND_TOL * (hi - lo)
    u = np.clip(u, lo, hi)
    return np.where(u - lo <= tol, lo, np.where(hi - u <= tol, hi, u))


# inputs, iterations, cost, converged, and the next solve's warm-start array (None: none)
SolveResult = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]


def result(
    shape: tuple[int, ...],
    U: np.ndarray,
    iterations: np.ndarray,
    cost: np.ndarray,
    converged: np.ndarray,
    warm: np.ndarray | None,
) -> SolveResult:
    """A solve's outputs in the problems' own batch shape (warm: the next solve's warm-start array, flat batch)."""
    lead = shape[:-2]
    return U.reshape(shape), iterations.reshape(lead), cost.reshape(lead), converged.reshape(lead), warm


@dataclass(frozen=True, eq=False)
class Problem:
    """A batch of horizon OCPs in one argument, so every solver sees the same data in the same order.

    Arrays are all torch or all numpy (a solver's array_api says which it works in); the leading batch
    dimensions (B,) are shared by x0, x_ref, u_prev and the U0 handed to solve.
    """

    ocp: HorizonOCP  # the cost and the model (its disturbance included)
    x0: Array  # (B, nx) measured states
    x_ref: Array  # (B, H, nx) reference states x_1..x_H
    u_prev: Array  # (B, nu) the inputs applied last (the rate penalty's u_{-1})
    low: Array  # (nu,) input lower bounds
    high: Array  # (nu,) input upper bounds


@dataclass(frozen=True)
class NoWarm:
    """No warm start beyond U0: a cold start, and all that solvers without memory ever return."""


NO_WARM = NoWarm()


def wrong_warm(solver: object, warm: object, accepted: str) -> TypeError:
    """The error for a warm state another solver made: it belongs to that solver's own iterates."""
    return TypeError(f"{type(solver).__name__} takes {accepted} as warm, got {type(warm).__name__}")


def cold_inputs(solver: object, U0: Tensor, warm: object) -> Tensor:
    """A leaf copy of U0 for the autograd solvers, which keep no warm state (one given is another solver's)."""
    if not isinstance(warm, NoWarm):
        raise wrong_warm(solver, warm, "NoWarm")
    return U0.clone().requires_grad_(True)


@dataclass(frozen=True, eq=False)
class SolveInfo:
    """Per-problem solver statistics, batched like the problems."""

    iterations: Array  # (B,) int
    cost: Array  # (B,) float
    converged: Array  # (B,) bool
    states: np.ndarray | None = None  # (B, H, nx) the states x_1..x_H the solution reaches, if the solver has them


class Solver(Protocol):
    """Minimise the OCP over U (B, H, nu) within [low, high], starting from U0 and the solver's warm state.

    array_api names the array library the solver works in ("torch" or "numpy"): NMPC.make_step hands it
    arrays of that kind, so batch-1 solves pay no conversions. warm is NO_WARM or a warm state this
    solver returned for the previous receding-horizon problem, whose plan shifted by one step is U0. A solver may
    also offer warm_step(ocp, x0, U0, x_ref, u_prev, low, high, warm) for the controller's one problem (numpy, no
    batch axis): solve()'s result for it without the batch handling, or None where solve() must run
    (LiftedGaussNewtonSolver's compiled real-time iteration).
    """

    array_api: str

    def solve(self, problem: Problem, U0: Array, warm: Any = NO_WARM) -> tuple[Array, SolveInfo, Any]:
        """The optimised inputs, their statistics and the warm state for the next (shifted) problem."""
        ...


OPTIONAL_FLAGS = (bool | None,)  # a flag whose null means "decided elsewhere"


def check_fields(settings: Any) -> None:
    """A solver's settings against their annotated types (its __post_init__): whole numbers and non-negative
    finite reals, flags as booleans, so that a bad value is one line when the solver is built, not a failed solve."""
    hints = typing.get_type_hints(type(settings))
    for f in dataclasses.fields(settings):
        value, kind = getattr(settings, f.name), hints.get(f.name)
        if value is None and kind in OPTIONAL_FLAGS:
            continue
        if kind is bool or kind in OPTIONAL_FLAGS:
            check = boolean()
        elif kind is int:
            check = whole(0)
        elif kind is float:
            check = real(0.0)
        else:
            continue
        expected = check(value, {})
        if expected is not None and kind in OPTIONAL_FLAGS:
            expected += " or null"
        if expected is not None:
            name = type(settings).__name__
            raise ValueError(f"{name}.{f.name}={value!r}; expected {expected}")
