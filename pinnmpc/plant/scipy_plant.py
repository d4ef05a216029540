"""The simulated robot: scipy RK45 over one zero-hold period, as in the paper.

A step whose sign(v) friction chatters (a joint at rest) is redone with the switches located
(pinnmpc.plant.stick_slip)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.integrate import solve_ivp

from pinnmpc.plant.base import Plant as Plant  # re-exported: the protocol beside its first plant
from pinnmpc.plant.base import PlantError as PlantError
from pinnmpc.plant.settings import ScipyPlantSettings
from pinnmpc.plant.stick_slip import ChatterError, coulomb_joints, flip_counter, stick_slip_step
from pinnmpc.systems.base import System


@dataclass
class ScipyPlant:
    """Zero-hold plant x_{k+1} = flow(x_k, u_k, tau) integrated by solve_ivp around the numpy rhs."""

    system: System
    tau: float
    method: str = ScipyPlantSettings.method  # the settings and their defaults: pinnmpc/plant/settings.py
    rtol: float = ScipyPlantSettings.rtol
    atol: float = ScipyPlantSettings.atol
    chatter_flips: int | None = ScipyPlantSettings.chatter_flips
    stick_slip_tighten: float = ScipyPlantSettings.stick_slip_tighten
    max_switches: int = ScipyPlantSettings.max_switches
    step_times: list[float] = field(default_factory=list)
    stick_slip_steps: int = 0  # steps redone with the switches located

    def __post_init__(self) -> None:
        if not self.tau > 0:
            raise ValueError(f"plant tau must be > 0, got {self.tau}")
        ScipyPlantSettings(  # the settings' own checks: one line naming the bad one
            method=self.method, rtol=self.rtol, atol=self.atol, chatter_flips=self.chatter_flips,
            stick_slip_tighten=self.stick_slip_tighten, max_switches=self.max_switches,
        )  # fmt: skip
        joints = coulomb_joints(self.system)
        self._velocities = [self.system.nq + j for j in joints]
        box, inputs = self.system.state_box, self.system.input_box
        mid = (np.add(box.low, box.high) / 2, np.add(inputs.low, inputs.high) / 2)
        self.system.rhs(*mid)  # once, untimed: the first call loads lazy imports (Pinocchio), not a plant step's cost

    def _fun(self, _t: float, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The system rhs on numpy arrays: no torch dispatch per scipy call. A non-finite one stops the step (RK45
        would otherwise shrink its step on NaN error estimates without end)."""
        dx = self.system.rhs(x, u)
        if not np.isfinite(dx).all():
            raise FloatingPointError(f"non-finite dx/dt {np.asarray(dx).tolist()} at x={x.tolist()}")
        return dx

    def _integrate(self, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
        """solve_ivp over one period; a step whose sign(v) friction chatters is redone by stick-slip modes."""
        fun = self._fun
        if self._velocities and self.chatter_flips is not None:
            fun = flip_counter(fun, self._velocities, self.chatter_flips)
        try:
            sol = solve_ivp(fun, (0.0, self.tau), x0, method=self.method, args=(u,), rtol=self.rtol, atol=self.atol)
        except ChatterError:
            tight = self.stick_slip_tighten
            self.stick_slip_steps += 1
            return stick_slip_step(
                self.system, x0, u, self.tau, self.method, self.rtol / tight, self.atol / tight, self.max_switches
            )
        if not sol.success:
            raise RuntimeError(sol.message)
        return sol.y[:, -1]

    def step(self, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
        """One zero-hold period; raises PlantError on failure or non-finite state."""
        x0 = np.asarray(x0, dtype=np.float64)
        u_t = np.asarray(u, dtype=np.float64)
        if not (np.all(np.isfinite(x0)) and np.all(np.isfinite(u_t))):
            raise PlantError(f"plant got a non-finite state or input: x0={x0.tolist()}, u={u_t.tolist()}")
        start = time.perf_counter()
        try:
            x1 = self._integrate(x0, u_t)
        except (ValueError, FloatingPointError, RuntimeError) as e:
            raise PlantError(f"plant integration failed from x0={x0.tolist()}, u={u_t.tolist()}: {e}") from e
        self.step_times.append(time.perf_counter() - start)
        if not np.all(np.isfinite(x1)):
            raise PlantError(f"plant state became non-finite from x0={x0.tolist()}, u={u_t.tolist()}")
        return x1
