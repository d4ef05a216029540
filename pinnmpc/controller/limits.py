"""Joint position limits with margin, as both controllers take them: the soft penalty's definition (JointLimits: where
it starts, the lookahead on the velocity towards a limit), the governor of references and the check of plans. The
network OCP's residuals are in ocp.py, the classical NMPC's symbolic cost in classical/limits.py."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import torch
from torch import Tensor

from pinnmpc.controller.array_backend import Array, read_only

LIMIT_KEYS = ("low", "high", "weight", "margin")
OPTIONAL_LIMIT_KEYS = ("lookahead",)


@dataclass(frozen=True)
class JointLimits:
    """Soft joint position limits on every predicted state (both controllers take the same ones).

    Per predicted state x_i and limited joint j (positions come first in the state) the residual is
    sqrt(weight) * (q_j - clip(q_j, low_j + margin, high_j - margin)): zero, with a zero Jacobian, while the joint
    keeps `margin` from both limits, so the problem is unchanged until a plan comes that close; beyond, the cost
    grows with the square of the excess. With a `lookahead` T the position checked is where the joint's velocity
    carries it in T when it moves towards that limit, q_j + T max(v_j, 0) against the upper one and q_j + T min(v_j, 0)
    against the lower: a plan then brakes before the limit instead of arriving at it at speed (on a robot slower to
    brake than the model, such arrivals crossed the limits). An infinite bound is no limit on that side; a joint with
    neither is not limited.
    """

    low: tuple[float, ...]
    high: tuple[float, ...]
    weight: float
    margin: float = 0.0
    lookahead: float = 0.0
    """s: how far ahead the velocity towards a limit counts (0: the position alone)."""

    def __post_init__(self) -> None:
        low, high = tuple(float(v) for v in self.low), tuple(float(v) for v in self.high)
        weight, margin, lookahead = float(self.weight), float(self.margin), float(self.lookahead)
        if len(low) != len(high):
            raise ValueError(f"joint_limits: low has {len(low)} entries, high {len(high)}; expected one per joint")
        if not (math.isfinite(weight) and weight > 0):
            raise ValueError(f"joint_limits.weight={self.weight!r}: expected a finite number > 0")
        if not (math.isfinite(margin) and margin >= 0):
            raise ValueError(f"joint_limits.margin={self.margin!r}: expected a finite number >= 0")
        if not (math.isfinite(lookahead) and lookahead >= 0):
            raise ValueError(f"joint_limits.lookahead={self.lookahead!r}: expected a finite number of seconds >= 0")
        for j, (lo, hi) in enumerate(zip(low, high)):
            if math.isnan(lo) or math.isnan(hi) or not lo + margin < hi - margin:
                raise ValueError(
                    f"joint_limits: joint {j} has low {lo:g}, high {hi:g} and margin {margin:g}; "
                    "expected low + margin < high - margin"
                )
        values = {"low": low, "high": high, "weight": weight, "margin": margin, "lookahead": lookahead}
        for name, value in values.items():
            object.__setattr__(self, name, value)

    @classmethod
    def from_config(cls, cfg: Mapping | JointLimits | None, nq: int) -> JointLimits | None:
        """The limits of a config node {low, high, weight, margin[, lookahead]} (None: none) for an arm with nq
        joints."""
        if cfg is None:
            return None
        if not isinstance(cfg, JointLimits):
            missing = [k for k in LIMIT_KEYS if k not in cfg]
            if missing:
                raise ValueError(f"joint_limits={dict(cfg)} lacks {missing}; expected {{{', '.join(LIMIT_KEYS)}}}")
            unknown = sorted(set(cfg) - {*LIMIT_KEYS, *OPTIONAL_LIMIT_KEYS})
            if unknown:
                known = ", ".join((*LIMIT_KEYS, *OPTIONAL_LIMIT_KEYS))
                raise ValueError(f"joint_limits has unknown keys {unknown}; expected {known}")
            cfg = cls(*(cfg[k] for k in LIMIT_KEYS), **{k: cfg[k] for k in OPTIONAL_LIMIT_KEYS if k in cfg})
        if len(cfg.low) != nq:
            raise ValueError(f"joint_limits has {len(cfg.low)} entries in low and high; this arm has {nq} joints")
        return cfg

    @cached_property
    def joints(self) -> np.ndarray:
        """Indices of the joints with a finite limit on at least one side (read-only; kept: a controller checks
        its plans against them every sample)."""
        return read_only(np.flatnonzero(np.isfinite(self.low) | np.isfinite(self.high)))

    @cached_property
    def inner(self) -> tuple[np.ndarray, np.ndarray]:
        """Where the penalty starts, (low + margin, high - margin), for the limited joints (read-only, kept)."""
        j = self.joints
        return read_only(np.asarray(self.low)[j] + self.margin), read_only(np.asarray(self.high)[j] - self.margin)

    @cached_property
    def _velocities(self) -> np.ndarray:
        """Where the limited joints' velocities sit in a state (positions first)."""
        return read_only(len(self.low) + self.joints)

    @cached_property
    def _numpy_indices(self) -> tuple[slice | np.ndarray, slice | np.ndarray]:
        """The limited joints' positions and velocities in a state as numpy indices: slices (views, no gathers)
        where the joints are consecutive, as every arm's here are, else the index arrays."""
        j, nq = self.joints, len(self.low)
        if j.size and np.array_equal(j, np.arange(j[0], j[0] + j.size)):
            return slice(int(j[0]), int(j[0]) + j.size), slice(nq + int(j[0]), nq + int(j[0]) + j.size)
        return j, self._velocities

    def governed(self, x_ref: np.ndarray) -> np.ndarray:
        """Reference states (..., nx; positions first) with every limited position past (limit - margin) moved onto
        it and its velocity there zeroed: where the arm may not follow, the tracking cost then pulls towards where the
        penalty starts instead of against it (a reference beyond it left plans chattering at the limits, crossing
        them from some starts); a reference inside is returned as it is."""
        j, velocities = self._numpy_indices
        low, high = self.inner
        q = x_ref[..., j]
        outside = (q < low) | (q > high)
        if not outside.any():
            return x_ref
        governed = np.array(x_ref, dtype=np.float64)
        governed[..., j] = np.clip(q, low, high)
        governed[..., velocities] = np.where(outside, 0.0, x_ref[..., velocities])
        return governed

    def reached(self, states: np.ndarray) -> np.ndarray:
        """Per problem, whether any state (B, ..., nx; positions first) lies where the penalty acts (none without a
        limited joint)."""
        low, high = self.inner
        ahead_low, ahead_high = self.ahead(np.asarray(states))
        return ((ahead_low < low) | (ahead_high > high)).reshape(ahead_low.shape[0], -1).any(-1)

    def ahead(self, states: Array) -> tuple[Array, Array]:
        """The positions the penalty checks against the lower and the upper limits (..., limited joints): each limited
        joint's position plus lookahead times its velocity where it moves towards that limit."""
        numpy = isinstance(states, np.ndarray)
        joints, velocities = self._numpy_indices if numpy else self._torch_indices
        q = states[..., joints]
        if not self.lookahead:
            return q, q
        v = states[..., velocities]
        if numpy:  # numpy's ufuncs: ndarray.clip's Python wrapper costs more than the arithmetic
            return q + self.lookahead * np.minimum(v, 0.0), q + self.lookahead * np.maximum(v, 0.0)
        return q + self.lookahead * v.clip(max=0.0), q + self.lookahead * v.clip(min=0.0)

    @cached_property
    def _torch_indices(self) -> tuple[Tensor, Tensor]:
        """joints and their velocities' places as torch indices (a read-only numpy index would be shared)."""
        return torch.tensor(self.joints), torch.tensor(self._velocities)


def as_float(mask: Array, scale: float) -> Array:
    """scale where a boolean mask holds, 0 elsewhere, as floats of either namespace."""
    return scale * (mask.to(torch.float64) if isinstance(mask, Tensor) else mask.astype(np.float64))
