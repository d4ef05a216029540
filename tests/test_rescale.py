"""Fine-tuning's output-scale widening (model.rescale_to_logs): the network's function is unchanged, its scale
holds the robot's miss, and a real training run starts from it."""

from __future__ import annotations

import torch

from pinnmpc.surrogate.checkpoint import load_surrogate
from pinnmpc.training.rescale import widen_heads


def test_widening_the_heads_keeps_the_function_and_raises_the_scale() -> None:
    net = load_surrogate(system="planar3").model
    gen = torch.Generator().manual_seed(0)
    x0 = torch.rand(64, net.nx, generator=gen, dtype=torch.float64) * 2 - 1
    u = torch.rand(64, 3, generator=gen, dtype=torch.float64) * 2 - 1
    t = torch.rand(64, 1, generator=gen, dtype=torch.float64) * net.t_max
    before, scale = net(t, x0, u), net.head_scale.clone()
    miss = scale * torch.tensor([50.0, 1.0, 0.5, 1000.0, 2.0, 0.1], dtype=torch.float64)
    new = widen_heads(net, miss)
    assert torch.allclose(net(t, x0, u), before, rtol=1e-12, atol=1e-14)
    assert torch.equal(new, torch.maximum(scale, miss)) and torch.equal(net.head_scale, new)
