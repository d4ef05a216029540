"""The actuation law's arithmetic in any array namespace (torch, numpy, CasADi), so the law is written once, and
where a servo settles against dry friction (the frozen-arm prior's drive)."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import casadi as ca
import numpy as np
import torch
from torch import Tensor

CASADI = SimpleNamespace(tanh=ca.tanh)  # the few functions the actuation law needs, for symbolic arguments


SETTLE_NEWTON_STEPS = 10  # Newton steps of settled_velocity from rest: 8 reach 1e-16 for C/K up to 1 s/rad at slope 50


def settled_velocity(w: Any, ratio: Any, slope: float) -> Any:
    """The root v of v = w - ratio tanh(slope v), where a servo commanded w settles against dry friction (K (w - v) =
    C tanh(slope v), ratio = C / K), by Newton from rest: the function is increasing, concave on the side of the root,
    so the steps rise monotonically onto it; one smooth formula in any array namespace, differentiable throughout."""
    ops = xp(w)
    v = 0 * w
    for _ in range(SETTLE_NEWTON_STEPS):
        th = ops.tanh(slope * v)
        v = v - (v - w + ratio * th) / (1 + ratio * slope * (1 - th * th))
    return v


def xp(a: Any) -> Any:
    """Array namespace of a: torch, numpy or CasADi, so the actuation law is written once."""
    if isinstance(a, np.ndarray):  # first: the plant asks thousands of times per step
        return np
    if isinstance(a, Tensor):
        return torch
    if isinstance(a, ca.SX | ca.MX | ca.DM):
        return CASADI
    return np
