"""Stable entry point: the PowerCube right-hand side, float64, batched, differentiable."""

from __future__ import annotations

from torch import Tensor

from pinnmpc.systems.powercube import DEFAULT_PARAMS
from pinnmpc.systems.powercube import rhs as _powercube_rhs

__all__ = ["rhs"]


def rhs(x: Tensor, u: Tensor) -> Tensor:
    """dx/dt of the nominal PowerCube for x (..., 4) and u (..., 2)."""
    if x.shape[-1] != 4 or u.shape[-1] != 2:
        raise ValueError(f"rhs expects x (..., 4) and u (..., 2), got x {tuple(x.shape)} and u {tuple(u.shape)}")
    return _powercube_rhs(x, u, DEFAULT_PARAMS)
