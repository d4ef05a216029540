"""Warm starts: a trained network widened without changing what it computes, so training adds capacity to it.

A network that has flattened under every loss setting may lack capacity, and starting a wider one from scratch
throws away hours of training. Widening (Chen et al. 2016, Net2Net) keeps the trained units and adds new ones
whose outgoing weights are zero: the wider network starts at the trained one's exact outputs and the optimiser
moves from there with all parameters free.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from pinnmpc.pinn import PINN
from pinnmpc.surrogate import load_surrogate
from pinnmpc.systems.base import System


def widened(base: PINN, hidden: Sequence[int], seed: int) -> PINN:
    """A copy of `base` with hidden widths `hidden` (same depth, none narrower) and the same outputs."""
    old = [layer.out_features for layer in base.net.layers[:-1]]
    new = [int(w) for w in hidden]
    if len(new) != len(old) or any(n < o for n, o in zip(new, old)):
        raise ValueError(
            f"model.hidden={new} cannot start from a network of hidden widths {old}: expected the same depth "
            f"({len(old)} layers) and no layer narrower"
        )
    model = PINN(**{**base.config, "hidden": new}).to(base.out_scale.dtype)
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for src, dst in zip(base.net.layers, model.net.layers):
            _embed(src, dst, generator)
        model.load_state_dict({**model.state_dict(), **_buffers(base)})
    return model


def _embed(src: nn.Linear, dst: nn.Linear, generator: torch.Generator) -> None:
    """dst = src in its leading block, the trained units deaf to new ones below them; new units' rows are fresh."""
    o, i = src.weight.shape
    fresh = torch.randn(dst.weight.shape, generator=generator, dtype=dst.weight.dtype)
    fresh *= (2.0 / sum(dst.weight.shape)) ** 0.5  # the Xavier-normal scale the network starts with
    fresh[:o, :i] = src.weight
    fresh[:o, i:] = 0.0  # the trained units ignore the new ones below them until training turns them on
    dst.weight.copy_(fresh)
    dst.bias.zero_()
    dst.bias[:o] = src.bias


def _buffers(model: PINN) -> dict[str, torch.Tensor]:
    """The normalisation and output-scale buffers, which do not depend on the widths."""
    return {k: v for k, v in model.state_dict().items() if not k.startswith("net.")}


def grown_model(system: System, path: str, tau: float, t_max: float, hidden: Sequence[int], seed: int) -> PINN:
    """The trained surrogate at `path` (init_from) widened to `hidden`, checked against this run's system."""
    surrogate = load_surrogate(path, state_names=tuple(system.state_names))
    base = surrogate.model
    for what, have, want in (("tau", surrogate.tau, tau), ("t_max", base.t_max, t_max)):
        if abs(have - want) > 1e-12:
            raise ValueError(f"init_from={path} was trained with {what}={have}; this run has {what}={want}")
    return widened(base, hidden, seed)
