"""Fine-tuning on a robot that misses the model by far more than the network's output scale: the scale widened
to the robot's one-period miss first, the network's function unchanged, so the optimiser can reach it."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from pinnmpc.robot_data.episodes import transitions
from pinnmpc.robot_data.logs import read_logs
from pinnmpc.surrogate.network import PINN
from pinnmpc.systems.base import System
from pinnmpc.systems.previous_input import WithPreviousInput, arm_system


def log_transitions(system: System, logs: Sequence[str]) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(t, x0, u, x1) of every transition in the logs up to one period: read once for the checks below (u with u_prev
    for a system that takes it)."""
    prev = isinstance(system, WithPreviousInput)
    return transitions(read_logs(list(logs), arm_system(system)), system.tau, previous_input=prev)


def period_miss(net: PINN, system: System, logged: tuple[Tensor, ...]) -> Tensor:
    """The network's RMS miss per state over every one-period transition of the logs (log_transitions)."""
    t, x0, u, x1 = logged
    at_tau = (t[:, 0] - system.tau).abs() <= 1e-9 * system.tau
    with torch.no_grad():
        pred = net(t[at_tau].to(net.out_scale.dtype), x0[at_tau], u[at_tau])
    return (pred - x1[at_tau]).square().mean(dim=0).sqrt()


def live_features(net: PINN, logged: tuple[Tensor, ...], floor: float = 1e-6) -> int:
    """How many units of the network's last hidden layer are alive (|activation| above floor) somewhere on the logs'
    transitions (log_transitions): a network that a prior already made exact can have none left, and no gradient
    then reaches its weights."""
    from pinnmpc.surrogate import mlp
    from pinnmpc.surrogate.network import TORCH

    t, x0, u, _ = logged
    dtype = net.out_scale.dtype
    pairs = net.net.pairs()
    width = pairs[-1][0].shape[1]
    identity = (torch.eye(width, dtype=dtype), torch.zeros(width, dtype=dtype))
    with torch.no_grad():
        h = mlp.value(TORCH, [*pairs[:-1], identity], net.net.activation, net._inputs(t.to(dtype), x0, u))
    return int((h.abs().amax(dim=0) > floor).sum())


def widen_heads(net: PINN, miss: Tensor) -> Tensor:
    """Each head's output scale raised to at least miss (its state's), the last layer's rows shrunk by the same
    factor: the same function, a scale the robot's misses fit in. Returns the new head scale."""
    old = net.head_scale.detach().clone()
    new = torch.maximum(old, miss[net.nx - net.n_head :].to(old.dtype))
    rows = (old / new).repeat(net.n_gates)  # the last layer's outputs run gate by gate, n_head each
    last = net.net.layers[-1]
    with torch.no_grad():
        last.weight.mul_(rows.to(last.weight.dtype)[:, None])
        last.bias.mul_(rows.to(last.bias.dtype))
        net.out_scale[net.nx - net.n_head :] = new
    return new
