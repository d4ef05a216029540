"""Section 4: how the cost of a batched OCP solve grows with horizon and batch size, and of one step with batch
size (PINN against torch RK4), with a plot of each."""

from __future__ import annotations

from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig

from pinnmpc.bench.common import controller_cfg, integrator_h, random_states
from pinnmpc.bench.step import torch_inputs
from pinnmpc.bench.timing import time_calls, timing_stats
from pinnmpc.controller.build import build_nmpc
from pinnmpc.plant.integrators import rk4_step
from pinnmpc.surrogate.checkpoint import Surrogate
from pinnmpc.systems.base import System
from pinnmpc.systems.sampling import uniform_box


def ocp_scaling_point(cfg: DictConfig, surrogate: Surrogate, horizon: int, batch: int) -> dict[str, float]:
    """Batched solves by the configured solver of random problems (states and references uniform in the box)."""
    sc = cfg.scaling
    nmpc = build_nmpc(controller_cfg(cfg, horizon=horizon), surrogate)
    box, nx, nu = surrogate.state_box, surrogate.nx, surrogate.nu
    seed = int(cfg.seed)
    x0 = uniform_box(batch, box.low, box.high, seed)
    x_ref = uniform_box(batch * horizon, box.low, box.high, seed + 1).reshape(batch, horizon, nx)
    U0 = torch.zeros(batch, horizon, nu, dtype=torch.float64).clamp(nmpc.low, nmpc.high)
    u_prev = U0[:, 0].clone()
    iters: list[float] = []

    def solve(_i: int) -> None:
        _, info, _ = nmpc.solve(x0, x_ref, U0, u_prev)
        iters.append(float(info.iterations.double().mean()))

    times = time_calls(solve, int(sc.repeats), int(sc.warmup))
    med = float(np.median(times))
    return {
        "horizon": horizon,
        "batch": batch,
        **timing_stats(times),
        "per_problem_median_s": med / batch,
        "problems_per_s": batch / med,
        "iterations_mean": float(np.mean(iters)),
    }


def step_scaling(cfg: DictConfig, system: System, surrogate: Surrogate) -> dict[str, list[float]]:
    """One-step cost vs batch size for the PINN and torch RK4: where batching pays off."""
    sc = cfg.scaling
    batches = [int(b) for b in sc.step_batch_sizes]
    x, u = random_states(system, max(batches), int(cfg.seed))
    h = integrator_h(surrogate.tau, cfg.step.h)
    methods = {
        "pinn_f64": (surrogate.step, torch_inputs(torch.float64)),
        "rk4_torch": (partial(rk4_step, system.rhs, tau=surrogate.tau, h=h), torch_inputs(torch.float64)),
    }
    out: dict[str, list[float]] = {"batch_sizes": [float(b) for b in batches]}
    with torch.no_grad():  # not inference_mode: a system may cache tensors its later autograd calls reuse
        for key, (call, prepare) in methods.items():
            medians = []
            for b in batches:
                args = prepare(x[:b], u[:b])
                times = time_calls(lambda _i, a=args, c=call: c(*a), int(sc.step_repeats), int(sc.step_warmup))
                medians.append(float(np.median(times)))
            out[f"{key}_median_s"] = medians
            out[f"{key}_per_sample_s"] = [m / b for m, b in zip(medians, batches)]
    return out


def bench_scaling(cfg: DictConfig, system: System, surrogate: Surrogate, run_dir: Path) -> dict[str, Any]:
    """OCP time vs horizon and batch size, one-step cost vs batch size, with a plot of each."""
    sc = cfg.scaling
    base_h = int(sc.base_horizon if sc.base_horizon is not None else cfg.controller.horizon)
    horizon_rows = [ocp_scaling_point(cfg, surrogate, int(h), int(sc.base_batch)) for h in sc.horizons]
    batch_rows = [ocp_scaling_point(cfg, surrogate, base_h, int(b)) for b in sc.batch_sizes]
    steps = step_scaling(cfg, system, surrogate)
    plots_written = write_plots(cfg, run_dir, horizon_rows, batch_rows, steps, base_h) if cfg.plots else []
    return {
        "base_horizon": base_h,
        "base_batch": int(sc.base_batch),
        "horizon": horizon_rows,
        "batch": batch_rows,
        "step": steps,
        "plots": plots_written,
    }


def write_plots(
    cfg: DictConfig,
    run_dir: Path,
    horizon_rows: list[dict[str, Any]],
    batch_rows: list[dict[str, Any]],
    steps: dict[str, list[float]],
    base_h: int,
) -> list[str]:
    """scaling_horizon.png, scaling_batch.png and scaling_step.png; the names written."""
    from pinnmpc.util import plots

    solver = str(cfg.controller.solver)
    figures = {
        "scaling_horizon.png": plots.scaling_figure(
            [r["horizon"] for r in horizon_rows],
            {f"time per solve (B={int(cfg.scaling.base_batch)})": [r["median_s"] for r in horizon_rows]},
            "horizon H [steps]",
            "median time [s]",
            f"OCP solve ({solver}) vs horizon",
        ),
        "scaling_batch.png": plots.scaling_figure(
            [r["batch"] for r in batch_rows],
            {
                "time per batched solve": [r["median_s"] for r in batch_rows],
                "time per problem": [r["per_problem_median_s"] for r in batch_rows],
            },
            "batch size B [problems]",
            "median time [s]",
            f"OCP solve ({solver}) vs batch size (H={base_h})",
        ),
        "scaling_step.png": plots.scaling_figure(
            steps["batch_sizes"],
            {
                "PINN float64, per call": steps["pinn_f64_median_s"],
                "RK4 torch, per call": steps["rk4_torch_median_s"],
                "PINN float64, per sample": steps["pinn_f64_per_sample_s"],
                "RK4 torch, per sample": steps["rk4_torch_per_sample_s"],
            },
            "batch size [states]",
            "median time [s]",
            "one step x_k -> x_k+1 vs batch size",
        ),
    }
    for name, fig in figures.items():
        plots.save_figure(fig, run_dir / name)
    return list(figures)
