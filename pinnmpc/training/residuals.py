"""Where a network breaks the physics: its scaled ODE residual at fresh collocation points, by state and time.

The training loss is the ODE residual dx/dt - f(x, u) of the network, divided per state by its residual unit
(output scale / t_max). Its RMS split by state and by bins of t over [0, t_max] shows what limits a network:
a stiff start of the step (large residuals in the first bin only), one state's rows outweighing the others
(module.kinematic_weight), or an even misfit everywhere (capacity or training time). `python -m pinnmpc.residuals`
runs run_residuals.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig
from torch import Tensor

from pinnmpc.surrogate.checkpoint import load_surrogate
from pinnmpc.surrogate.network import PINN
from pinnmpc.systems.base import System
from pinnmpc.systems.settings import job_system
from pinnmpc.training.data import collocation_box, lhs_box
from pinnmpc.training.job_settings import validate_residuals
from pinnmpc.util.io import save_json


def scaled_residual(system: System, model: PINN, n: int, seed: int) -> tuple[Tensor, Tensor]:
    """t and the explicit residual per state in the network's residual units, on n LHS points of its box."""
    pts = lhs_box(n, *collocation_box(system, model.t_max), seed).to(model.out_scale.dtype)
    nx = system.state_box.dim
    t, x0, u = pts[:, :1], pts[:, 1 : 1 + nx], pts[:, 1 + nx :]
    with torch.no_grad():
        x, dxdt = model.with_time_derivative(t, x0, u)
        r = system.residual(x, dxdt, u, "explicit") / model.residual_unit
    return t[:, 0].double().contiguous(), r.double()


def residual_table(system: System, model: PINN, n: int, bins: int, seed: int) -> dict[str, Any]:
    """RMS of the scaled residual per t bin and state, overall per state, and each state's share of the sum."""
    t, r = scaled_residual(system, model, n, seed)
    edges = torch.linspace(0.0, model.t_max, bins + 1, dtype=torch.float64)
    which = torch.bucketize(t, edges[1:-1], right=True)
    sums = torch.zeros(bins, r.shape[1], dtype=torch.float64).index_add_(0, which, r.square())
    counts = torch.bincount(which, minlength=bins).clamp_min(1).double()
    per_bin = (sums / counts[:, None]).sqrt()
    mean_square = r.square().mean(dim=0)
    names = list(system.state_names)
    return {
        "points": int(n),
        "t_edges_s": edges.tolist(),
        "state_names": names,
        "residual_unit": [float(v) for v in model.residual_unit.double()],
        "rms_by_bin": per_bin.tolist(),
        "rms": {k: float(v) for k, v in zip(names, mean_square.sqrt())},
        "share": {k: float(v) for k, v in zip(names, mean_square / mean_square.sum())},
    }


def run_residuals(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """The table of a surrogate as residuals.json, and residuals.png (a heat map)."""
    system = job_system(cfg, validate_residuals)
    surrogate = load_surrogate(
        cfg.checkpoint, system=system.name if cfg.checkpoint is None else None, state_names=system.state_names
    )
    result = residual_table(system, surrogate.model, int(cfg.points), int(cfg.bins), int(cfg.seed))
    save_json(run_dir / "residuals.json", result)
    if cfg.plots:  # matplotlib only when a figure is wanted
        from pinnmpc.util.plots import residual_figure, save_figure

        edges, rms = np.asarray(result["t_edges_s"]), np.asarray(result["rms_by_bin"])
        title = f"{system.name}: RMS scaled ODE residual by time in the step ({cfg.points} LHS points)"
        save_figure(residual_figure(edges, rms, result["state_names"], title), run_dir / "residuals.png")
    return result
