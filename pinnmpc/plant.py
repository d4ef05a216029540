"""The simulated robot: scipy RK45 over one zero-hold period, as in the paper."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.integrate import solve_ivp

from pinnmpc.systems.base import System


class PlantError(RuntimeError):
    """The plant integration failed: the closed loop must stop, not continue with garbage."""


@dataclass
class ScipyPlant:
    """Zero-hold plant x_{k+1} = flow(x_k, u_k, tau) integrated by solve_ivp around the torch rhs."""

    system: System
    tau: float
    method: str = "RK45"
    rtol: float = 1e-3  # scipy's default, as the paper
    atol: float = 1e-6  # scipy's default, as the paper
    step_times: list[float] = field(default_factory=list)

    def __post_init__(self) -> None:
        if not self.tau > 0:
            raise ValueError(f"plant tau must be > 0, got {self.tau}")

    def _fun(self, _t: float, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The system rhs on numpy arrays: no torch dispatch per scipy call."""
        return self.system.rhs(x, u)

    def step(self, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
        """One zero-hold period; raises PlantError on failure or non-finite state."""
        x0 = np.asarray(x0, dtype=np.float64)
        u_t = np.asarray(u, dtype=np.float64)
        if not (np.all(np.isfinite(x0)) and np.all(np.isfinite(u_t))):
            raise PlantError(f"plant got a non-finite state or input: x0={x0.tolist()}, u={u_t.tolist()}")
        start = time.perf_counter()
        try:
            sol = solve_ivp(
                self._fun, (0.0, self.tau), x0, method=self.method, args=(u_t,), rtol=self.rtol, atol=self.atol
            )
        except (ValueError, FloatingPointError) as e:
            raise PlantError(f"plant integration failed from x0={x0.tolist()}, u={u_t.tolist()}: {e}") from e
        self.step_times.append(time.perf_counter() - start)
        if not sol.success:
            raise PlantError(f"plant integration failed from x0={x0.tolist()}, u={u_t.tolist()}: {sol.message}")
        x1 = sol.y[:, -1]
        if not np.all(np.isfinite(x1)):
            raise PlantError(f"plant state became non-finite from x0={x0.tolist()}, u={u_t.tolist()}")
        return x1
