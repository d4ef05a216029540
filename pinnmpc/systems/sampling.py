"""Uniform samples of an arm's boxes: held-out points for validation, benchmarks and the prior's rates."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from pinnmpc.systems.base import System


def uniform_box(n: int, low: Sequence[float], high: Sequence[float], seed: int) -> Tensor:
    """n independent uniform points: held-out sets must not share the LHS structure."""
    rng = np.random.default_rng(seed)
    return torch.from_numpy(rng.uniform(low, high, size=(n, len(low))))


def random_pairs(system: System, n: int, seed: int) -> tuple[Tensor, Tensor]:
    """n held-out (x0, u), each uniform over the training box (seeds seed and seed + 1)."""
    x0 = uniform_box(n, system.state_box.low, system.state_box.high, seed)
    return x0, uniform_box(n, system.input_box.low, system.input_box.high, seed + 1)
