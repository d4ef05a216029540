"""What every simulated robot offers the closed loop: one zero-hold period at a time, timed."""

from __future__ import annotations

from typing import Protocol

import numpy as np


class PlantError(RuntimeError):
    """The plant integration failed: the closed loop must stop, not continue with garbage."""


class Plant(Protocol):
    """A robot driven one control period at a time with the input held: x_{k+1} = plant.step(x_k, u_k)."""

    tau: float  # control period, s
    step_times: list[float]  # wall time of each step, s
    stick_slip_steps: int  # steps redone with friction switches located (0 where the plant has none)

    def step(self, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The state one period later; raises PlantError when the step fails or leaves the finite numbers."""
        ...
