"""`python -m pinnmpc.residuals`: where a trained network breaks the physics, per state and per time in the step.

The training loss is the ODE residual dx/dt - f(x, u) of the network, divided per state by its residual unit
(output scale / t_max). Its RMS split by state and by bins of t over [0, t_max] shows what limits a network:
a stiff start of the step (large residuals in the first bin only), one state's rows outweighing the others
(module.kinematic_weight), or an even misfit everywhere (capacity or training time).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import hydra
import numpy as np
from omegaconf import DictConfig

from pinnmpc.cli import check_choices, run_job
from pinnmpc.surrogate.checkpoint import load_surrogate
from pinnmpc.training.residuals import residual_table
from pinnmpc.util.io import save_json
from pinnmpc.util.settings import job_system, validate_residuals


def _summary(m: dict[str, Any], run_dir: Path) -> str:
    """One line: RMS and loss share per state."""
    rms = ", ".join(f"{k} {v:.2e} ({100 * m['share'][k]:.0f}%)" for k, v in m["rms"].items())
    return f"RMS scaled residual (share of the sum of squares): {rms}; outputs in {run_dir}"


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


@hydra.main(version_base="1.3", config_path="../conf", config_name="residuals")
def main(cfg: DictConfig) -> None:
    """CLI: the per-state RMS and where the outputs went."""
    run_job(lambda run_dir: run_residuals(cfg, run_dir), "pinnmpc.residuals", _summary)


if __name__ == "__main__":
    check_choices("pinnmpc.residuals")
    main()
