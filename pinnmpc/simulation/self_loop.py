"""Open-loop rollouts of the paper's self-loop test: the same inputs through the network and through the plant, and
the test as `python -m pinnmpc.self_loop` runs it (run_self_loop)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig

from pinnmpc.plant.scipy_plant import ScipyPlant
from pinnmpc.simulation.settings import validate_self_loop
from pinnmpc.surrogate.checkpoint import Surrogate, load_surrogate
from pinnmpc.systems.base import System
from pinnmpc.systems.previous_input import takes_previous_input, with_previous
from pinnmpc.systems.settings import job_system
from pinnmpc.util.io import save_json, save_npz


def sine_inputs(steps: int, amplitude: Sequence[float]) -> np.ndarray:
    """The paper's excitation, one amplitude per input: u_k = a sin(2 pi k / (steps - 1)) (paper: a = (0.5, -0.5))."""
    a = np.asarray(amplitude, dtype=np.float64)
    if a.ndim != 1 or not np.all(np.isfinite(a)):
        raise ValueError(f"amplitude={list(np.atleast_1d(a))}; expected one finite number per input")
    return np.sin(np.linspace(0.0, 2 * np.pi, int(steps)))[:, None] * a[None, :]


def rollout_surrogate(surrogate: Surrogate, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Self-loop: each prediction at tau becomes the next x0 (a network given the previous input gets the input before
    each one, the first its own: a lag that starts settled)."""
    xs = [torch.as_tensor(x0, dtype=torch.float64)]
    inputs = torch.as_tensor(u, dtype=torch.float64)
    if takes_previous_input(surrogate):
        inputs = with_previous(inputs)
    with torch.no_grad():
        for uk in inputs:
            xs.append(surrogate.step(xs[-1], uk))
    return torch.stack(xs).numpy()


def rollout_plant(plant: ScipyPlant, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The same inputs applied to the plant."""
    xs = [np.asarray(x0, dtype=np.float64)]
    for uk in u:
        xs.append(plant.step(xs[-1], uk))
    return np.array(xs)


def run_self_loop(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Both rollouts, the error per state, metrics.json, self_loop.npz and a plot."""
    system: System = job_system(cfg, validate_self_loop)
    surrogate = load_surrogate(
        cfg.checkpoint, system=system.name if cfg.checkpoint is None else None, state_names=system.state_names
    )
    u = sine_inputs(cfg.steps, cfg.amplitude)
    x0 = np.asarray(cfg.x0, dtype=np.float64)
    x_pinn = rollout_surrogate(surrogate, x0, u)
    x_plant = rollout_plant(ScipyPlant(system, surrogate.tau), x0, u)
    t = surrogate.tau * np.arange(len(u) + 1)
    err = np.abs(x_pinn - x_plant)
    names = system.state_names
    result = {
        "steps": int(cfg.steps),
        "tau": surrogate.tau,
        "mae": {n: float(v) for n, v in zip(names, err.mean(0))},
        "max_abs_error": {n: float(v) for n, v in zip(names, err.max(0))},
        "final_abs_error": {n: float(v) for n, v in zip(names, err[-1])},
    }
    save_npz(run_dir / "self_loop.npz", t=t, x_plant=x_plant, x_pinn=x_pinn, u=u)
    save_json(run_dir / "metrics.json", result)
    if cfg.plots:
        from pinnmpc.util import plots

        fig = plots.self_loop_figure(
            t,
            x_plant,
            x_pinn,
            u,
            plots.Labels.of(system),
            title=f"{system.name}: self-loop, {cfg.steps} steps of tau = {surrogate.tau} s",
        )
        plots.save_figure(fig, run_dir / "self_loop.png")
    return result
