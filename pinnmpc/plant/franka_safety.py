"""The safety layer between any controller and a Franka arm: commands clipped to the velocity limits and slowed
before the joint limits, so that a controller whose model is not the robot cannot drive a joint past its limit."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from pinnmpc.plant.base import PlantError
from pinnmpc.systems.base import System


class SafetyLayer:
    """Each command made safe against the latest measured state; events counts what it changed."""

    def __init__(self, system: System, tau: float, settings: Any) -> None:
        """Limits from the system (joint limits less plant.limit_margin, the input box); braking from the settings."""
        if system.joint_limits is None:
            raise ValueError(f"plant=franka: system {system.name} has no joint_limits; expected a Franka arm's")
        low, high = np.asarray(system.joint_limits.low, float), np.asarray(system.joint_limits.high, float)
        self.limits = np.stack([low, high])
        self.low, self.high = low + settings.limit_margin, high - settings.limit_margin
        self.vmax = np.minimum(np.abs(system.input_box.low), np.abs(system.input_box.high)).astype(float)
        self.tau, self.brake = float(tau), float(settings.brake_acceleration)
        self.events = {"clipped_commands": 0, "slowed_commands": 0, "watchdog_stops": 0, "non_finite_commands": 0}

    def cap_velocity(self, limits: Sequence[float]) -> None:
        """Tighten the velocity limits to the robot interface's own (franky refuses faster commands)."""
        self.vmax = np.minimum(self.vmax, np.asarray(limits, dtype=float))

    def check_target(self, q: np.ndarray) -> None:
        """A start or target configuration inside the joint limits less the margin, or one line saying which not."""
        bad = np.flatnonzero((q < self.low) | (q > self.high))
        if bad.size:
            j = int(bad[0])
            raise PlantError(
                f"plant=franka: joint {j + 1} target {q[j]:.4f} rad lies outside [{self.low[j]:.4f}, "
                f"{self.high[j]:.4f}] (joint limits less plant.limit_margin); the arm was not moved"
            )

    def allowed(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The fastest speed toward each limit from q: the arm covers at most the room left in one period (the
        command holds a period before the next can brake) and can brake to rest before the limit."""
        room_up, room_down = np.maximum(self.high - q, 0.0), np.maximum(q - self.low, 0.0)

        def speed(room: np.ndarray) -> np.ndarray:
            return np.minimum(np.sqrt(2.0 * self.brake * room), room / self.tau)

        return speed(room_up), speed(room_down)

    def command(self, u: np.ndarray, x: np.ndarray) -> np.ndarray:
        """u clipped to the velocity limits and slowed before the joint limits at the measured state x."""
        nq = len(self.vmax)
        if not np.all(np.isfinite(u)):
            self.events["non_finite_commands"] += 1
            u = np.where(np.isfinite(u), u, 0.0)
        clipped = np.clip(u, -self.vmax, self.vmax)
        if np.any(clipped != u):
            self.events["clipped_commands"] += 1
        up, down = self.allowed(np.asarray(x[:nq], dtype=float))
        safe = np.clip(clipped, -np.minimum(down, self.vmax), np.minimum(up, self.vmax))
        if np.any(safe != clipped):
            self.events["slowed_commands"] += 1
        return safe
