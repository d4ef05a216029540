"""Multi-stage training: measure what a trained network still gets wrong and set up a correction network for it."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from pinnmpc.surrogate.checkpoint import load_surrogate
from pinnmpc.surrogate.network import PINN
from pinnmpc.surrogate.staged import StagedPINN
from pinnmpc.systems.base import System
from pinnmpc.training.data import random_pairs, reference_flow
from pinnmpc.training.residuals import scaled_residual


def one_step_rmse(system: System, model: PINN, tau: float, n: int, h: float, seed: int) -> Tensor:
    """RMSE per state of x(tau) on n random (x0, u) against fine RK4: the size the correction has to reach."""
    x0, u = random_pairs(system, n, seed)
    dtype = model.out_scale.dtype
    with torch.no_grad():
        x1 = model(torch.full_like(x0[:, :1], tau).to(dtype), x0.to(dtype), u.to(dtype)).double()
    return (x1 - reference_flow(system, x0, u, tau, h)).square().mean(dim=0).sqrt()


def residual_level(system: System, model: PINN, n: int, seed: int) -> float:
    """RMS of the explicit ODE residual in the network's residual units over n LHS points of its training box."""
    return float(scaled_residual(system, model, n, seed)[1].square().mean().sqrt())


def staged_model(
    system: System,
    base_path: str,
    tau: float,
    hidden: Sequence[int],
    error_scale: float,
    first_layer_gain: float,
    last_layer_gain: float,
    samples: int,
    h: float,
    seed: int,
) -> StagedPINN:
    """A correction network on top of a trained surrogate, its output scaled to the base's one-step error."""
    if not (error_scale > 0 and first_layer_gain > 0 and last_layer_gain >= 0 and samples >= 1):
        raise ValueError(
            "need stage.error_scale > 0, stage.first_layer_gain > 0, stage.last_layer_gain >= 0 and "
            f"stage.samples >= 1; got {error_scale}, {first_layer_gain}, {last_layer_gain}, {samples}"
        )
    surrogate = load_surrogate(base_path, nx=system.state_box.dim, nu=system.input_box.dim)
    if abs(surrogate.tau - tau) > 1e-12:
        raise ValueError(f"stage.base {base_path} was trained for tau={surrogate.tau}; this run has tau={tau}")
    base = surrogate.model
    scale = (error_scale * one_step_rmse(system, base, tau, samples, h, seed)).clamp_min(1e-12)
    level = residual_level(system, base, samples, seed + 2)
    correction = {**base.config, "hidden": [int(w) for w in hidden], "output_scale": scale.tolist()}
    model = StagedPINN(base.config, correction, level).to(base.out_scale.dtype)
    model.base.load_state_dict(base.state_dict())
    with torch.no_grad():  # a fresh start near the base network, its first layer optionally sharper
        model.correction.net.layers[0].weight.mul_(first_layer_gain)
        model.correction.net.layers[-1].weight.mul_(last_layer_gain)
    return model
