"""The network's smooth activations with their slopes (forward-mode tangents) and curvatures (second-order
models), written once over `Ops`: the few primitives they need from an array library. `TORCH` trains the
nn.Module, `NUMPY` serves the controller's batch-1 calls, and pinnmpc.surrogate.casadi_network builds the
CasADi form that the export writes, all from the formulas below."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from scipy.special import expit
from torch.nn import functional


@dataclass(frozen=True)
class Ops:
    """An array library as the activations and the MLP passes (pinnmpc.surrogate.mlp) see it."""

    name: str  # the library, for messages
    tanh: Callable[[Any], Any]
    sin: Callable[[Any], Any]
    cos: Callable[[Any], Any]
    sigmoid: Callable[[Any], Any]  # 1 / (1 + exp(-a)), computed stably
    softplus: Callable[[Any], Any]  # log(1 + exp(a)), computed stably
    affine: Callable[[Any, Any, Any], Any]  # a layer z -> z W + b, with W in the library's own layout
    linear: Callable[[Any, Any], Any]  # the same layer without its bias: what tangents go through
    widen: Callable[[Any], Any]  # a per-unit factor (..., width) made to scale tangents (..., k, width)


NUMPY = Ops(
    "numpy", np.tanh, np.sin, np.cos, expit, lambda a: np.logaddexp(0.0, a),
    affine=lambda z, w, b: z @ w + b,  # w stored transposed (in, out): row vectors times W^T
    linear=lambda z, w: z @ w,
    widen=lambda s: s[..., None, :],
)  # fmt: skip
TORCH = Ops(
    "torch", torch.tanh, torch.sin, torch.cos, torch.sigmoid, functional.softplus,
    affine=functional.linear,  # nn.Linear's (out, in) weight
    linear=lambda z, w: z @ w.T,
    widen=lambda s: s.unsqueeze(-2),
)  # fmt: skip


def _tanh(ops: Ops, a: Any) -> tuple[Any, Any]:
    """tanh and its slope, reusing the value."""
    y = ops.tanh(a)
    return y, 1 - y * y


def _sin(ops: Ops, a: Any) -> tuple[Any, Any]:
    """sin (SIREN-style) and its slope."""
    return ops.sin(a), ops.cos(a)


def _silu(ops: Ops, a: Any) -> tuple[Any, Any]:
    """SiLU (swish) and its slope from one sigmoid: smooth, non-saturating."""
    s = ops.sigmoid(a)
    y = a * s
    return y, s + y * (1 - s)


def _softplus(ops: Ops, a: Any) -> tuple[Any, Any]:
    """softplus and its slope, the sigmoid."""
    return ops.softplus(a), ops.sigmoid(a)


def _tanh_curvature(ops: Ops, a: Any, y: Any, slope: Any) -> Any:
    """tanh'' from its value and slope."""
    return -2 * y * slope


def _sin_curvature(ops: Ops, a: Any, y: Any, slope: Any) -> Any:
    """sin'' = -sin."""
    return -y


def _silu_curvature(ops: Ops, a: Any, y: Any, slope: Any) -> Any:
    """SiLU'' = s (1 - s) (2 + a (1 - 2 s)), s = sigmoid(a), as ((1 - s - s) a + 2) s (1 - s)."""
    s = ops.sigmoid(a)
    rest = 1 - s
    return ((rest - s) * a + 2) * s * rest


def _softplus_curvature(ops: Ops, a: Any, y: Any, slope: Any) -> Any:
    """softplus'' = s (1 - s), s = sigmoid(a) = the slope."""
    return slope * (1 - slope)


TANGENTS: dict[str, Callable[[Ops, Any], tuple[Any, Any]]] = {  # value and slope: the choices of model.activation
    "tanh": _tanh,
    "sin": _sin,
    "silu": _silu,
    "softplus": _softplus,
}
VALUES: dict[str, Callable[[Ops, Any], Any]] = {  # value alone, for the cheapest evaluation
    "tanh": lambda ops, a: ops.tanh(a),
    "sin": lambda ops, a: ops.sin(a),
    "silu": lambda ops, a: a * ops.sigmoid(a),
    "softplus": lambda ops, a: ops.softplus(a),
}
CURVATURES: dict[str, Callable[[Ops, Any, Any, Any], Any]] = {  # second derivatives, for second-order models
    "tanh": _tanh_curvature,
    "sin": _sin_curvature,
    "silu": _silu_curvature,
    "softplus": _softplus_curvature,
}


def check_activation(name: str) -> str:
    """name, if it is one of the smooth activations; else one clear error listing them."""
    if name not in TANGENTS:
        raise ValueError(f"unknown activation {name!r}; expected one of {sorted(TANGENTS)} (smooth)")
    return name


def with_curvature(ops: Ops, name: str, a: Any) -> tuple[Any, Any, Any]:
    """Value, slope and curvature of activation `name` at a: what a second-order pass needs per layer."""
    y, slope = TANGENTS[name](ops, a)
    return y, slope, CURVATURES[name](ops, a, y, slope)
