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
from omegaconf import DictConfig

from pinnmpc.cli import check_choices, run_job


def _summary(m: dict[str, Any], run_dir: Path) -> str:
    """One line: RMS and loss share per state."""
    rms = ", ".join(f"{k} {v:.2e} ({100 * m['share'][k]:.0f}%)" for k, v in m["rms"].items())
    return f"RMS scaled residual (share of the sum of squares): {rms}; outputs in {run_dir}"


@hydra.main(version_base="1.3", config_path="../conf", config_name="residuals")
def main(cfg: DictConfig) -> None:
    """CLI: the per-state RMS and where the outputs went."""
    # imported here: --help and a refused setting answer before torch loads
    from pinnmpc.training.residuals import run_residuals

    run_job(lambda run_dir: run_residuals(cfg, run_dir), "pinnmpc.residuals", _summary)


if __name__ == "__main__":
    check_choices("pinnmpc.residuals")
    main()
