"""`python -m pinnmpc.self_loop`: the paper's open-loop test, the PINN fed its own predictions, against the plant."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import hydra
import numpy as np
from omegaconf import DictConfig

from pinnmpc.cli import check_choices, run_job
from pinnmpc.plant.scipy_plant import ScipyPlant
from pinnmpc.simulation.open_loop import rollout_plant, rollout_surrogate, sine_inputs
from pinnmpc.surrogate.checkpoint import load_surrogate
from pinnmpc.systems.base import System
from pinnmpc.util.io import save_json, save_npz
from pinnmpc.util.settings import job_system, validate_self_loop


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


@hydra.main(version_base="1.3", config_path="../conf", config_name="self_loop")
def main(cfg: DictConfig) -> None:
    """CLI: headline numbers and where the outputs went."""
    run_job(lambda run_dir: run_self_loop(cfg, run_dir), "pinnmpc.self_loop", _summary)


def _summary(m: dict[str, Any], run_dir: Path) -> str:
    """One line: MAE per state against the plant."""
    mae = ", ".join(f"{k} {v:.2e}" for k, v in m["mae"].items())
    return f"self-loop {m['steps']} steps, MAE vs plant: {mae}; outputs in {run_dir}"


if __name__ == "__main__":
    check_choices("pinnmpc.self_loop")
    main()
