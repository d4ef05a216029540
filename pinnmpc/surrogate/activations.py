"""The network's smooth activations with their slopes (forward-mode tangents) and curvatures (second-order
models), for torch (training, the nn.Module) and for numpy (the controller's batch-1 calls): one table per array
library, the curvature formulas that need only arithmetic written once for both."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from scipy.special import expit
from torch import Tensor, nn


def _tanh_curvature(a: Any, y: Any, slope: Any) -> Any:
    """tanh'' from its value and slope."""
    return -2 * y * slope


def _sin_curvature(a: Any, y: Any, slope: Any) -> Any:
    """sin'' = -sin."""
    return -y


def _softplus_curvature(a: Any, y: Any, slope: Any) -> Any:
    """Softplus'' = s (1 - s), s = sigmoid(a) = the slope."""
    return slope * (1 - slope)


# torch ------------------------------------------------------------------------------------------------------


def _tanh_torch(a: Tensor) -> tuple[Tensor, Tensor]:
    """tanh and its derivative, reusing the value."""
    y = torch.tanh(a)
    return y, 1 - y * y


def _sin_torch(a: Tensor) -> tuple[Tensor, Tensor]:
    """sin (SIREN-style) and its derivative."""
    return torch.sin(a), torch.cos(a)


def _silu_torch(a: Tensor) -> tuple[Tensor, Tensor]:
    """SiLU (swish) and its derivative: smooth, non-saturating."""
    s = torch.sigmoid(a)
    y = a * s
    return y, s + y * (1 - s)


def _softplus_torch(a: Tensor) -> tuple[Tensor, Tensor]:
    """Softplus and its derivative."""
    return nn.functional.softplus(a), torch.sigmoid(a)


def _silu_curvature_torch(a: Tensor, y: Tensor, slope: Tensor) -> Tensor:
    """SiLU'' = s (1 - s) (2 + a (1 - 2 s)), s = sigmoid(a)."""
    s = torch.sigmoid(a)
    return s * (1 - s) * (2 + a * (1 - 2 * s))


ACTIVATIONS: dict[str, Callable[[Tensor], tuple[Tensor, Tensor]]] = {
    "tanh": _tanh_torch,
    "sin": _sin_torch,
    "silu": _silu_torch,
    "softplus": _softplus_torch,
}
CURVATURES: dict[str, Callable[[Tensor, Tensor, Tensor], Tensor]] = {  # second derivatives, for second-order models
    "tanh": _tanh_curvature,
    "sin": _sin_curvature,
    "silu": _silu_curvature_torch,
    "softplus": _softplus_curvature,
}


# numpy (in place where it saves allocations) -------------------------------------------------------------------


def _tanh(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """tanh and its slope, for forward-mode tangents."""
    y = np.tanh(a)
    slope = y * y
    np.subtract(1.0, slope, out=slope)
    return y, slope


def _sin(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """sin and its slope, for forward-mode tangents."""
    return np.sin(a), np.cos(a)


def _silu(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """SiLU and its slope from one sigmoid, for forward-mode tangents."""
    s = expit(a)
    y = a * s
    slope = 1.0 - s  # silu' = s + silu (1 - s), in place
    slope *= y
    slope += s
    return y, slope


def _softplus(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """softplus and its slope, for forward-mode tangents."""
    return np.logaddexp(0.0, a), 1.0 / (1.0 + np.exp(-a))


def _silu_value(a: np.ndarray) -> np.ndarray:
    """SiLU alone, for value-only calls."""
    y = expit(a)
    y *= a
    return y


def _softplus_value(a: np.ndarray) -> np.ndarray:
    """softplus alone, for value-only calls."""
    return np.logaddexp(0.0, a)


def _silu_curvature_numpy(a: np.ndarray, y: np.ndarray, slope: np.ndarray) -> np.ndarray:
    """SiLU'' from the sigmoid (second-order Jacobians)."""
    s = expit(a)
    return s * (1.0 - s) * (2.0 + a * (1.0 - 2.0 * s))


def _silu_full(a: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """SiLU value, slope and curvature from one sigmoid, in place where possible (second-order Jacobians)."""
    s = expit(a)
    y = a * s
    rest = 1.0 - s
    slope = y * rest
    slope += s
    curvature = rest - s  # s (1 - s) (2 + a (1 - 2 s))
    curvature *= a
    curvature += 2.0
    curvature *= s
    curvature *= rest
    return y, slope, curvature


NUMPY_ACTIVATIONS = {"tanh": _tanh, "sin": _sin, "silu": _silu, "softplus": _softplus}  # as ACTIVATIONS
VALUE_ACTIVATIONS = {"tanh": np.tanh, "sin": np.sin, "silu": _silu_value, "softplus": _softplus_value}  # no slope
NUMPY_CURVATURES = {  # second derivatives, as CURVATURES
    "tanh": _tanh_curvature,
    "sin": _sin_curvature,
    "silu": _silu_curvature_numpy,
    "softplus": _softplus_curvature,
}
FUSED = {"silu": _silu_full}  # value, slope and curvature sharing work; others compose the two above
