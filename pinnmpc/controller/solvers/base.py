"""What every OCP solver shares: the result type, the protocol, and projection onto the input box."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
from torch import Tensor

from pinnmpc.controller.ocp import HorizonOCP

BOUND_TOL = 1e-12  # relative to the box width: closer than this to a bound counts as on it


def project(u: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Clip to the box and put values within rounding of a bound exactly on it (the answer a user sees)."""
    tol = BOUND_TOL * (hi - lo)
    u = np.clip(u, lo, hi)
    return np.where(u - lo <= tol, lo, np.where(hi - u <= tol, hi, u))


def result(shape: tuple[int, ...], U, iterations, cost, converged, warm):
    """A solve's outputs in the problems' own batch shape (warm: the next solve's prior, flat batch)."""
    lead = shape[:-2]
    return U.reshape(shape), iterations.reshape(lead), cost.reshape(lead), converged.reshape(lead), warm


@dataclass
class SolveInfo:
    """Per-problem solver statistics, batched like the problems."""

    iterations: Tensor  # (B,) int
    cost: Tensor  # (B,) float
    converged: Tensor  # (B,) bool
    sensitivities: np.ndarray | None = None  # (B, H, nx, H*nu) d x_i / d U near the solution, for the next solve
    states: np.ndarray | None = None  # (B, H, nx) the states x_1..x_H the solution reaches on the surrogate


class Solver(Protocol):
    """Minimise the OCP over U (B, H, nu) within [low, high], starting from U0.

    array_api names the array library the solver works in ("torch" or "numpy"): NMPC.make_step
    hands it arrays of that kind, so batch-1 solves pay no conversions. Solvers with accepts_prior
    take prior= (the last solve's SolveInfo field named by their prior_kind) as a warm start beyond U0.
    """

    array_api: str

    def solve(
        self,
        ocp: HorizonOCP,
        x0: Tensor,
        U0: Tensor,
        x_ref: Tensor,
        u_prev: Tensor,
        low: Tensor,
        high: Tensor,
    ) -> tuple[Tensor, SolveInfo]:
        """Return the optimised inputs and statistics."""
        ...
