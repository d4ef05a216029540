"""Offset-free MPC's disturbance estimate, shared by the network and the classical NMPC.

Every predicted step gets an additive d: the model's one-step prediction errors, filtered by a gain and bounded per
state. Optionally the last two errors are averaged first (a zero at the sampling rate's Nyquist frequency), so an
error that flips sign every sample, as a robot's stick-slip seen at the control rate does, stays out of d while a
lasting offset still enters it, half a sample later.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np


def disturbance_bound(d_max: Sequence[float] | None, nx: int, gain: float) -> np.ndarray | None:
    """Validated offset-free settings (gain in [0, 1], nx non-negative bounds); the bound as an array."""
    if not 0.0 <= gain <= 1.0:
        raise ValueError(f"controller.disturbance.gain={gain}; expected a number in [0, 1]")
    bound = None if d_max is None else np.array(d_max, dtype=np.float64)
    if bound is not None and (bound.shape != (nx,) or np.any(~(bound >= 0))):
        raise ValueError(
            f"controller.disturbance.max_abs={list(d_max)} (system.control.disturbance_max); expected null or {nx} "
            "numbers >= 0, one per state"
        )
    return bound


def filtered_disturbance(
    d: np.ndarray | None, error: np.ndarray, gain: float, bound: np.ndarray | None
) -> np.ndarray | None:
    """Offset-free MPC's estimate after one more (finite: OffsetFree.update skips the others) prediction error:
    filtered by the gain, bounded per state."""
    d = np.zeros_like(error) if d is None else d
    d = d + gain * (error - d)
    return d if bound is None else np.minimum(np.maximum(d, -bound), bound)  # np.clip's values, less overhead


@dataclass
class OffsetFree:
    """The disturbance estimate of one closed loop: update(error) after each sample, reset() at a new run."""

    nx: int
    """States per prediction error."""
    gain: float = 0.0
    """0: off (the paper's controller); 1: d = the last error; in (0, 1): exponential filter of the errors."""
    max_abs: Sequence[float] | None = None
    """Per-state bound on |d| (None: unbounded)."""
    notch: bool = False
    """Average the last two errors before the filter: an error alternating every sample does not enter d."""
    value: np.ndarray | None = field(default=None, init=False)
    """The estimate the next solve predicts with (None: none yet)."""

    def __post_init__(self) -> None:
        self.gain = float(self.gain)
        self._bound = disturbance_bound(self.max_abs, self.nx, self.gain)
        if not isinstance(self.notch, bool | np.bool_):
            raise ValueError(f"controller.disturbance.notch={self.notch!r}; expected true or false")
        self.reset()

    @property
    def on(self) -> bool:
        """Whether the estimate is used at all."""
        return self.gain > 0.0

    def reset(self) -> None:
        """Forget the estimate and the last error: the start of a new run."""
        self.value = None
        self._previous: np.ndarray | None = None

    def update(self, error: np.ndarray) -> np.ndarray | None:
        """The estimate after one more prediction error x - F(x_prev, u_prev); a non-finite one is skipped."""
        if not np.isfinite(error).all():
            return self.value
        seen = error if not self.notch or self._previous is None else 0.5 * (error + self._previous)
        self._previous = error
        self.value = filtered_disturbance(self.value, seen, self.gain, self._bound)
        return self.value


def late_notch(notch: bool, when_late: bool, delay_periods: int) -> bool:
    """The notch of a run: as set, or (controller.disturbance.notch=null) on where the plant holds each input a period
    late: there the estimate, fed back through the prediction of the period ahead, rang at the sampling rate's
    Nyquist frequency on franky-sim after a start a few mrad off the reference (docs/franka.md)."""
    return bool(notch) or (bool(when_late) and delay_periods > 0)
