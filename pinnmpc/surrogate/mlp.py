"""The MLP's passes written once over an array library (pinnmpc.surrogate.activations.Ops): the value, the
value with tangents (forward-mode derivatives along k directions), and the second-order passes the physics
loss of a second-order network needs. Layers are (W, b) pairs in the library's layout (`Ops.affine`); the
last layer has no activation."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from pinnmpc.surrogate.activations import CURVATURES, TANGENTS, VALUES, Ops

Layers = Sequence[tuple[Any, Any]]


def value(ops: Ops, layers: Layers, activation: str, z: Any) -> Any:
    """The network's output at z: the cheapest path."""
    act = VALUES[activation]
    for w, b in layers[:-1]:
        z = act(ops, ops.affine(z, w, b))
    w, b = layers[-1]
    return ops.affine(z, w, b)


def tangent(ops: Ops, layers: Layers, activation: str, z: Any, dz: Any) -> tuple[Any, Any]:
    """Output and its directional derivatives along dz (..., k, n_in)."""
    act = TANGENTS[activation]
    for w, b in layers[:-1]:
        a, da = ops.affine(z, w, b), ops.linear(dz, w)
        z, slope = act(ops, a)
        dz = da * ops.widen(slope)
    w, b = layers[-1]
    return ops.affine(z, w, b), ops.linear(dz, w)


def second(ops: Ops, layers: Layers, activation: str, z: Any, dz: Any) -> tuple[Any, Any, Any]:
    """Output, first and second derivative along one direction dz (..., n_in) in which the input is linear."""
    act, curvature = TANGENTS[activation], CURVATURES[activation]
    ddz = None
    for w, b in layers[:-1]:
        a, da = ops.affine(z, w, b), ops.linear(dz, w)
        z, slope = act(ops, a)
        bend = curvature(ops, a, z, slope) * da * da
        dz = slope * da
        ddz = bend if ddz is None else bend + slope * ops.linear(ddz, w)
    w, b = layers[-1]
    return ops.affine(z, w, b), ops.linear(dz, w), ops.linear(ddz, w)


def mixed(ops: Ops, layers: Layers, activation: str, z: Any, dt: Any, dd: Any) -> tuple[Any, Any, Any, Any]:
    """Output, derivative along dt (..., n_in), along each of dd (..., k, n_in), and the mixed second ones."""
    act, curvature = TANGENTS[activation], CURVATURES[activation]
    cross = None
    for w, b in layers[:-1]:
        a, at, ad = ops.affine(z, w, b), ops.linear(dt, w), ops.linear(dd, w)
        z, slope = act(ops, a)
        bend = ops.widen(curvature(ops, a, z, slope) * at) * ad
        slope_k = ops.widen(slope)
        cross = bend if cross is None else bend + slope_k * ops.linear(cross, w)
        dt, dd = slope * at, slope_k * ad
    w, b = layers[-1]
    return ops.affine(z, w, b), ops.linear(dt, w), ops.linear(dd, w), ops.linear(cross, w)
