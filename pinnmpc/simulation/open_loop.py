"""Open-loop rollouts of the paper's self-loop test: the same inputs through the network and through the plant."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from pinnmpc.plant.scipy_plant import ScipyPlant
from pinnmpc.surrogate.checkpoint import Surrogate


def sine_inputs(steps: int, amplitude: Sequence[float]) -> np.ndarray:
    """The paper's excitation, one amplitude per input: u_k = a sin(2 pi k / (steps - 1)) (paper: a = (0.5, -0.5))."""
    a = np.asarray(amplitude, dtype=np.float64)
    if a.ndim != 1 or not np.all(np.isfinite(a)):
        raise ValueError(f"amplitude={list(np.atleast_1d(a))}; expected one finite number per input")
    return np.sin(np.linspace(0.0, 2 * np.pi, int(steps)))[:, None] * a[None, :]


def rollout_surrogate(surrogate: Surrogate, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Self-loop: each prediction at tau becomes the next x0."""
    xs = [torch.as_tensor(x0, dtype=torch.float64)]
    with torch.no_grad():
        for uk in torch.as_tensor(u, dtype=torch.float64):
            xs.append(surrogate.step(xs[-1], uk))
    return torch.stack(xs).numpy()


def rollout_plant(plant: ScipyPlant, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The same inputs applied to the plant."""
    xs = [np.asarray(x0, dtype=np.float64)]
    for uk in u:
        xs.append(plant.step(xs[-1], uk))
    return np.array(xs)
