"""The joint-limit guard: the last word on each input, so the position limits hold on an arm that is not the model.

The OCPs' soft limits (JointLimits) keep plans inside; a robot that is not the model (a load, motor inertia, dry
friction) or a plan the solver left at the penalty's kink can still carry the arm past. The guard looks one
period ahead with the controller's own model, corrected by what that model missed over the last period (the model
monitor's one-step miss, positions and velocities), and where the next position, or where the next velocity
carries it within `lookahead` periods more, would lie past (limit - margin), it moves the input by the least
(box-scaled) amount that puts it back on that edge, within the input box. The margin grows with how much the miss
changed over the last period (what the correction cannot foresee). Both NMPCs (nmpc, exact, casadi) take it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np

from pinnmpc.controller.ocp import JointLimits

StepJacobian = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]  # (x, u) -> (F(x, u), dF/du)

GUARD_KEYS = ("margin", "lookahead", "miss_gain", "iterations")
MISS_DECAY = 0.8  # per period: the remembered miss fades to a fifth in about seven periods


@dataclass
class LimitGuard:
    """Per sample: filter(x, u) -> the input to apply; reset() at a new run."""

    limits: JointLimits
    """The joints and their limits (the OCP's; its margin and weight are the OCP's business)."""
    step: StepJacobian
    """The controller model's undisturbed one step and its input Jacobian."""
    tau: float
    """The control period, s."""
    margin: float = 0.002
    """rad the guarded next position keeps from each limit."""
    lookahead: float = 1.0
    """Periods of the next velocity added to the next position in the check (0: the position alone)."""
    miss_gain: float = 1.0
    """The margin grows by this times the change of the one-step position miss over the last period."""
    iterations: int = 3
    """Relinearisations of the correction (the model is nonlinear in u)."""
    active: int = field(default=0, init=False)
    """Samples whose input the guard changed since the last reset."""

    def __post_init__(self) -> None:
        for name in ("margin", "lookahead", "miss_gain"):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"controller.limit_guard.{name}={getattr(self, name)!r}; expected a number >= 0")
            setattr(self, name, value)
        if isinstance(self.iterations, bool) or not isinstance(self.iterations, int) or self.iterations < 1:
            raise ValueError(f"controller.limit_guard.iterations={self.iterations!r}; expected a whole number >= 1")
        j = self.limits.joints
        self._joints = j
        self._low, self._high = np.asarray(self.limits.low)[j], np.asarray(self.limits.high)[j]
        self.reset()

    @classmethod
    def from_config(
        cls, cfg: Mapping | None, limits: JointLimits | None, step: StepJacobian, tau: float
    ) -> LimitGuard | None:
        """The guard of controller.limit_guard (None, or no limits: none)."""
        if cfg is None or limits is None or not limits.joints.size:
            return None
        unknown = sorted(set(cfg) - set(GUARD_KEYS))
        if unknown:
            raise ValueError(f"controller.limit_guard has unknown keys {unknown}; expected any of {list(GUARD_KEYS)}")
        return cls(limits, step, float(tau), **dict(cfg))

    def reset(self) -> None:
        """Forget the last prediction and the miss: the start of a new run."""
        self._predicted: np.ndarray | None = None
        self._miss: np.ndarray | None = None
        self.active = 0

    def _update_miss(self, x: np.ndarray) -> np.ndarray | float:
        """The margin's growth: miss_gain times the size of the model's one-step position miss on the guarded joints,
        filtered over the last periods (what the model cannot foresee; a robot's stick-slip flips its sign)."""
        if self._predicted is None:
            return 0.0
        miss = np.abs(x - self._predicted)[self._joints]
        if np.all(np.isfinite(miss)):
            self._miss = miss if self._miss is None else np.maximum(miss, MISS_DECAY * self._miss)
        return 0.0 if self._miss is None else self.miss_gain * self._miss

    def _excess(
        self, nxt: np.ndarray, b: np.ndarray, edge_lo: np.ndarray, edge_hi: np.ndarray, tau_v: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Per guarded side: how far the checked positions lie past their edge, and their rows of d/du."""
        nq = nxt.size // 2
        j = self._joints
        q, v = nxt[j], nxt[nq + j]
        rows_q, rows_v = b[j], b[nq + j]
        ahead, rows_ahead = q + tau_v * v, rows_q + tau_v * rows_v
        values = np.concatenate([q - edge_hi, ahead - edge_hi, edge_lo - q, edge_lo - ahead])
        rows = np.concatenate([rows_q, rows_ahead, -rows_q, -rows_ahead])
        return values, rows

    def filter(self, x: np.ndarray, u: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
        """The input to apply at measured state x: u, or the nearest input whose guarded next state keeps the margin."""
        margin = self.margin + self._update_miss(x)
        edge_lo, edge_hi = self._low + margin, self._high - margin
        # the edges may not cross for a tiny range: the middle then
        mid = 0.5 * (self._low + self._high)
        edge_lo, edge_hi = np.minimum(edge_lo, mid), np.maximum(edge_hi, mid)
        width = np.maximum(high - low, 1e-12)
        out = np.array(u, dtype=np.float64)
        nxt, b = self.step(x, out)
        changed = False
        for _ in range(self.iterations):
            values, rows = self._excess(nxt, b, edge_lo, edge_hi, self.lookahead * self.tau)
            on = values > 0
            if not on.any():
                break
            changed = True
            g, c = rows[on] * width, -values[on]  # in box-scaled inputs s = (u - u0) / width
            s = np.linalg.lstsq(g, c, rcond=None)[0]
            out = np.clip(out + s * width, low, high)
            nxt, b = self.step(x, out)
        self.active += int(changed)
        self._predicted = nxt
        return out
