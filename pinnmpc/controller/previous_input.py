"""NMPC on a network that takes the previous input: the measured state joined by the input applied last.

The OCP runs on the states s = (x, u_prev) of pinnmpc.surrogate.previous_input.PreviousInputFlow; the controller
measures x alone and knows what it applied, so it forms s itself, pads the reference (u_prev is not tracked: its
weight is zero) and answers the closed loop in the arm's states (its model monitor, its disturbance estimate).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from torch import Tensor

from pinnmpc.controller.nmpc import NMPC, _array


def padded_weight(weight: Sequence | None, extra: int) -> Any:
    """A state weight (diagonal list or matrix) for the arm's states, with zero weight on `extra` states after them."""
    if weight is None:
        return None
    w = np.asarray(weight, dtype=np.float64)
    if w.ndim == 1:
        return np.concatenate((w, np.zeros(extra))).tolist()
    out = np.zeros((w.shape[0] + extra, w.shape[1] + extra))
    out[: w.shape[0], : w.shape[1]] = w
    return out.tolist()


@dataclass
class PreviousInputNMPC(NMPC):
    """NMPC whose model also takes the input of the period before: make_step(x, x_ref) in the arm's states."""

    def __post_init__(self) -> None:
        self.arm_nx = self.ocp.nx - self.ocp.nu  # the arm's states; the OCP's carry u_prev after them
        super().__post_init__()

    def reset(self) -> None:
        """As NMPC.reset; the inputs before the last one are the last one (a lag that starts settled)."""
        super().reset()
        self._before = self._u_prev.copy()
        self._older = self._u_prev.copy()  # the input before _before: a plant a period late still runs _before

    def describe(self) -> dict[str, Any]:
        """NMPC's description, and that its model takes the previous input."""
        return {**super().describe(), "previous_input": True}

    def _memory(self) -> np.ndarray:
        """The input the period about to start follows: the last one applied, or with a plant a period late the one
        before it (the last one then runs over the coming period, which the plan's start predicts)."""
        return self._before if self.delay_periods else self._u_prev

    def make_step(self, x: np.ndarray | Tensor, x_ref: np.ndarray | Tensor) -> np.ndarray:
        """Input to apply now, given the measured arm state (nx,) and the next H reference states (H, nx)."""
        x0, ref = _array(x), _array(x_ref)
        if x0.shape != (self.arm_nx,):
            raise ValueError(f"the state must have {self.arm_nx} entries, got shape {x0.shape}")
        if ref.ndim != 2 or ref.shape[-1] != self.arm_nx:
            raise ValueError(f"x_ref must be (H, {self.arm_nx}) reference states, got shape {ref.shape}")
        first = self._last is None and not self.delay_periods  # the run's first input, which runs at once
        before = self._u_prev.copy()
        s = np.concatenate((x0, self._memory()))
        padded = self._padded(len(ref))  # u_prev untracked (weight 0): zeros after the arm's states
        padded[:, : self.arm_nx] = ref
        u = super().make_step(s, padded)
        self._older, self._before = self._before, before
        if first:  # the actuator starts settled at it (as the plant and the logs take it), not at the cold start's
            self._older, self._before = u.copy(), u.copy()
            self._last, self._predicted = (np.concatenate((x0, u)), u.copy()), None
        return u

    def _padded(self, rows: int) -> np.ndarray:
        """The reference buffer (rows, nx) in the OCP's states, kept: NMPC.make_step copies what it is given."""
        kept = getattr(self, "_reference", None)
        if kept is None or kept.shape[0] != rows:
            kept = self._reference = np.zeros((rows, self.ocp.nx))
        return kept

    def prediction_error(self, x_prev: np.ndarray, u_prev: np.ndarray, x: np.ndarray) -> np.ndarray:
        """What the model missed over the last period, x - F(x_prev, u_prev, the input before it), in the arm's
        states: the input before is the controller's own record where u_prev is the one it applied last (or, with a
        plant a period late, the one before that, which that plant ran over the last period), else u_prev (a lag that
        had settled)."""
        u_prev = np.asarray(u_prev, dtype=np.float64)
        before = u_prev
        for applied, preceding in ((self._u_prev, self._before), (self._before, self._older)):
            if u_prev.shape == applied.shape and bool((u_prev == applied).all()):  # np.array_equal, unwrapped
                before = preceding
                break
        s = np.concatenate((np.asarray(x_prev, dtype=np.float64), before))
        nxt = np.concatenate((np.asarray(x, dtype=np.float64), u_prev))
        return self.ocp.prediction_error(s, u_prev, nxt)[: self.arm_nx]

    @property
    def disturbance(self) -> np.ndarray | None:
        """The disturbance estimate on the arm's states (None: off or not estimated yet)."""
        d = self.ocp.disturbance
        return None if d is None else d[: self.arm_nx]
