"""Receding-horizon controller: make_step(x) -> u, with warm start and a safe fallback."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from pinnmpc.controller.ocp import HorizonOCP
from pinnmpc.controller.solvers import SolveInfo, Solver
from pinnmpc.surrogate import Surrogate


@dataclass
class StepStats:
    """What one OCP solve did, for metrics.json and debugging."""

    time_s: float
    iterations: int
    cost: float
    converged: bool
    fallback: bool


@dataclass
class NMPC:
    """NMPC on a surrogate: solves the horizon OCP, applies the first input, shifts the rest as warm start."""

    ocp: HorizonOCP
    solver: Solver
    u_low: Sequence[float]
    u_high: Sequence[float]
    warm_start: bool = True
    stats: list[StepStats] = field(default_factory=list)

    def __post_init__(self) -> None:
        nu = self.ocp.nu
        self.low = torch.as_tensor(self.u_low, dtype=torch.float64)
        self.high = torch.as_tensor(self.u_high, dtype=torch.float64)
        if self.low.shape != (nu,) or self.high.shape != (nu,):
            raise ValueError(
                f"input bounds must have {nu} entries each, got {list(self.u_low)} and {list(self.u_high)}"
            )
        if torch.any(self.low > self.high):
            raise ValueError(f"input lower bound {self.low.tolist()} exceeds upper bound {self.high.tolist()}")
        self.reset()

    @property
    def horizon(self) -> int:
        """Prediction horizon H."""
        return self.ocp.horizon

    @property
    def surrogate(self) -> Surrogate:
        """The model the controller predicts with."""
        return self.ocp.surrogate

    def reset(self) -> None:
        """Forget the warm start and the last applied input (start of a new run)."""
        self.U = torch.zeros(self.horizon, self.ocp.nu, dtype=torch.float64).clamp(self.low, self.high)
        self.u_prev = self.U[0].clone()
        self.stats = []

    def clip(self, u: Tensor) -> Tensor:
        """Project onto the input box."""
        return torch.maximum(torch.minimum(u, self.high), self.low)

    def solve(self, x0: Tensor, x_ref: Tensor, U0: Tensor, u_prev: Tensor) -> tuple[Tensor, SolveInfo]:  # noqa: N803
        """Batched OCP: x0 (B, nx), x_ref (B, H, nx), U0 (B, H, nu), u_prev (B, nu)."""
        if x_ref.shape[-2] != self.horizon:
            raise ValueError(f"x_ref must cover the horizon: got {x_ref.shape[-2]} steps, expected {self.horizon}")
        U, info = self.solver.solve(self.ocp, x0, self.clip(U0), x_ref, u_prev, self.low, self.high)  # noqa: N806
        return self.clip(U), info

    def make_step(self, x: np.ndarray | Tensor, x_ref: np.ndarray | Tensor) -> np.ndarray:
        """Input to apply now, given the measured state and the next H reference states."""
        x0 = torch.as_tensor(np.asarray(x, dtype=np.float64))
        ref = torch.as_tensor(np.asarray(x_ref, dtype=np.float64))
        start = time.perf_counter()
        fallback = False
        try:
            U, info = self.solve(x0[None], ref[None], self.U[None], self.u_prev[None])  # noqa: N806
            U = U[0]  # noqa: N806
            ok = bool(torch.all(torch.isfinite(U))) and bool(torch.isfinite(info.cost).all())
        except (RuntimeError, FloatingPointError, np.linalg.LinAlgError):  # e.g. a singular solve on NaN outputs
            ok, info = False, None
        if not ok:
            fallback = True
            # self.U is already the previous plan shifted: its first entry is the input planned for now
            U = self.clip(torch.nan_to_num(self.U, nan=0.0, posinf=0.0, neginf=0.0))  # noqa: N806
        elapsed = time.perf_counter() - start
        self.U = self._shifted(U) if self.warm_start else torch.zeros_like(U).clamp(self.low, self.high)
        self.u_prev = U[0].clone()
        self.stats.append(
            StepStats(
                time_s=elapsed,
                iterations=int(info.iterations[0]) if info is not None else 0,
                cost=float(info.cost[0]) if info is not None else float("nan"),
                converged=bool(info.converged[0]) if info is not None and not fallback else False,
                fallback=fallback,
            )
        )
        return U[0].numpy().copy()

    @staticmethod
    def _shifted(U: Tensor) -> Tensor:  # noqa: N803
        """Warm start for the next solve: drop the applied input, repeat the last one."""
        return torch.cat((U[1:], U[-1:]), dim=0)
