"""`python -m pinnmpc.capacity`: can the configured network represent the one-step map? (training/capacity.py)"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig

from pinnmpc.cli import check_choices, run_job, say


def _summary(m: dict[str, Any], run_dir: Path) -> str:
    """The validation RMSE per state against its target, and where the outputs went."""
    targets = m["targets"] or [None] * len(m["state_names"])
    parts = []
    for name, value, target in zip(m["state_names"], m["val_rmse"], targets):
        mark = "" if target is None else (" (target met)" if value <= target else f" ({value / target:.1f}x target)")
        parts.append(f"{name} {value:.2e}{mark}")
    net = f"{m['model']['hidden']} {m['model']['activation']} ({m['dtype']})"
    end = "stopped: no decrease from a fresh L-BFGS history, " if m["stopped"] == "no decrease" else ""
    return (
        f"direct fit of {net} to x(tau), {m['steps']} L-BFGS calls ({m['resets']} history resets) in "
        f"{m['seconds'] / 60:.1f} min, {end}validation RMSE: "
        f"{', '.join(parts)}\noutputs in {run_dir} (surrogate.pt: the fitted network, right at t = tau only)"
    )


@hydra.main(version_base="1.3", config_path="../conf", config_name="capacity")
def main(cfg: DictConfig) -> None:
    """CLI: the one-step error the configured network reaches by direct fitting, and where the outputs went."""
    # imported here: --help and a refused setting answer before torch loads
    from pinnmpc.training.capacity import run_capacity

    overrides = hydra.core.hydra_config.HydraConfig.get().overrides.task
    command = " ".join(["python -m pinnmpc.capacity", *overrides])
    prog = "pinnmpc.capacity"
    run_job(lambda run_dir: run_capacity(cfg, run_dir, command, lambda line: say(line, run_dir, prog)), prog, _summary)


if __name__ == "__main__":
    check_choices("pinnmpc.capacity")
    main()
