"""Time-basis check (`python -m pinnmpc.time_basis`): can the gates of ic='gated' span the flow's time dependence?

A gated network writes x(t) - x0 = scale * sum_k g_k(t) N_k(t, x0, u) with g_0 = t / t_max and
g_k = 1 - exp(-t / T_k) for the relaxation times T_k of system.network.time_basis. With each N_k a low-degree
polynomial in t over one step (the smooth time dependence a network builds easily), that is a per-trajectory
least-squares fit of the true increment; what it misses the network has to build from its time input through
units over a normalised t, which a stiff mode much faster than the fastest gate makes hard. This check fits true
trajectories (fine RK4), shows the misfit per state, and which relaxation times added to the basis reduce it
most: a cheap check before a long training. The misfit is no bound (a network can go below it): compare
bases with it, and add gates where a state's misfit is near or above its one-step target.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig
from torch import Tensor

from pinnmpc.plant.integrators import n_steps, rk4_fixed
from pinnmpc.surrogate.network import time_gates
from pinnmpc.systems.base import System
from pinnmpc.systems.sampling import random_pairs
from pinnmpc.systems.settings import job_system
from pinnmpc.training.job_settings import validate_time_basis
from pinnmpc.util.io import save_json


def flow_increments(
    system: System, tau: float, t_max: float, n: int, samples: int, h: float, seed: int
) -> tuple[Tensor, Tensor]:
    """Times t_j = j tau / samples up to t_max and the true increments x(t_j) - x0 (T, n, nx) on n random (x0, u):
    an even grid weights every part of the step alike, so it must be fine enough for the fastest mode."""
    x0, u = random_pairs(system, n, seed)
    dt = tau / samples
    count = int(np.floor(t_max / dt + 1e-9))
    sub = n_steps(dt, h)
    x, out = x0, [torch.zeros_like(x0)]
    with torch.no_grad():
        for _ in range(count):
            x = rk4_fixed(system.fast_rhs, x, u, dt / sub, sub)
            out.append(x - x0)
    return dt * torch.arange(count + 1, dtype=torch.float64), torch.stack(out)


def gate_misfit(
    t: Tensor, increments: Tensor, t_max: float, basis: Sequence[float], at: int, degree: int = 0
) -> dict[str, list[float]]:
    """RMS per state of the least-squares fit of every trajectory's increment on the gates times polynomials of
    `degree` in t: over all t, and at t[at] (a fit's last points miss most, so the value at tau depends on how far
    t_max reaches beyond it)."""
    gates = time_gates(t[:, None], t_max, torch.tensor(list(basis), dtype=torch.float64))[0]
    powers = (t[:, None] / t_max) ** torch.arange(degree + 1, dtype=torch.float64)
    gates = (gates[:, :, None] * powers[:, None, :]).flatten(1)  # g_k(t) (t / t_max)^j: N_k smooth in t
    flat = increments.reshape(len(t), -1)
    coef = torch.linalg.lstsq(gates, flat).solution
    miss = (flat - gates @ coef).reshape(increments.shape)
    return {
        "rms_at_tau": miss[at].square().mean(dim=0).sqrt().tolist(),
        "rms": miss.square().mean(dim=(0, 1)).sqrt().tolist(),
    }


def _score(misfit: dict[str, list[float]], size: np.ndarray) -> float:
    """Worst state's misfit over the step relative to its typical increment: the state a basis serves worst."""
    return float(np.max(np.asarray(misfit["rms"]) / size))


def basis_report(
    system: System,
    basis: Sequence[float],
    candidates: Sequence[float],
    greedy: int,
    degree: int,
    tau: float,
    t_max: float,
    n: int,
    dt: float,
    h: float,
    seed: int,
) -> dict[str, Any]:
    """The basis's misfit, each candidate added alone, and `greedy` candidates added one by one, best first."""
    samples = max(1, round(tau / dt))
    t, inc = flow_increments(system, tau, t_max, n, samples, h, seed)
    size = inc[samples].square().mean(dim=0).sqrt().clamp_min(1e-12).numpy()
    basis = [float(v) for v in basis]
    fresh = [float(c) for c in candidates if float(c) not in basis]
    fits: dict[tuple[float, ...], dict[str, list[float]]] = {}

    def fit(trial: list[float]) -> dict[str, list[float]]:
        """gate_misfit of one basis, each basis fitted once (the greedy's first round is the single additions)."""
        if tuple(trial) not in fits:
            fits[tuple(trial)] = gate_misfit(t, inc, t_max, trial, samples, degree)
        return fits[tuple(trial)]

    single = [{"added": c, **fit([*basis, c])} for c in fresh]
    chosen, steps = list(basis), []
    for _ in range(min(greedy, len(fresh))):
        best = min((c for c in fresh if c not in chosen), key=lambda c: _score(fit([*chosen, c]), size))
        chosen.append(best)
        steps.append({"time_basis": list(chosen), **fit(chosen)})
    return {
        "state_names": list(system.state_names),
        "tau": tau,
        "t_max": t_max,
        "points": n,
        "increment_rms_at_tau": size.tolist(),
        "degree": degree,
        "basis": {"time_basis": basis, **fit(basis)},
        "single": single,
        "greedy": steps,
    }


def run_time_basis(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """time_basis.json, and time_basis.png (misfit per state for the basis and its greedy extensions)."""
    system = job_system(cfg, validate_time_basis)
    result = basis_report(
        system,
        list(cfg.time_basis),
        list(cfg.candidates),
        int(cfg.greedy),
        int(cfg.degree),
        float(system.tau),
        float(cfg.t_max),
        int(cfg.points),
        float(cfg.dt),
        float(cfg.h),
        int(cfg.seed),
    )
    targets = (cfg.system.get("targets") or {}).get("one_step_rmse")
    result["targets"] = None if targets is None else list(targets)
    result["near_target"] = float(cfg.near_target)
    save_json(run_dir / "time_basis.json", result)
    if cfg.plots:
        _draw(result, f"{system.name}: gate misfit over [0, t_max] ({cfg.points} random steps)", targets, run_dir)
    return result


def _draw(result: dict[str, Any], title: str, targets: Sequence[float | None] | None, run_dir: Path) -> None:
    """time_basis.png: the basis and its greedy extensions (matplotlib imported only when a figure is wanted)."""
    from pinnmpc.util.plots import basis_figure, save_figure

    rows = [result["basis"], *result["greedy"]]
    labels = [str(r["time_basis"]) for r in rows]
    save_figure(
        basis_figure([r["rms"] for r in rows], labels, result["state_names"], targets, title),
        run_dir / "time_basis.png",
    )
