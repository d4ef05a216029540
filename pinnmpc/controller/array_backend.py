"""Torch-or-numpy helpers shared by the problem and the shooting code, so neither imports the other for them."""

from __future__ import annotations

from types import ModuleType

import numpy as np
import torch
from torch import Tensor

Array = Tensor | np.ndarray
Nd = np.ndarray  # the numpy solvers' arrays (float64), short enough for their many-argument signatures


def xp_of(a: Array) -> ModuleType:
    """Array namespace of a (torch or numpy)."""
    return torch if isinstance(a, Tensor) else np


def cat(parts: list[Array], axis: int) -> Array:
    """Concatenate in either namespace."""
    return torch.cat(parts, axis) if isinstance(parts[0], Tensor) else np.concatenate(parts, axis)


def read_only(a: np.ndarray) -> np.ndarray:
    """a, made read-only: an array kept and shared (between samples, solves or users) that no one may change."""
    a.setflags(write=False)
    return a
