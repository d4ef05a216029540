"""`python -m pinnmpc.self_loop`: the paper's open-loop test, the PINN fed its own predictions, against the plant."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig

from pinnmpc.cli import check_choices, run_job


@hydra.main(version_base="1.3", config_path="../conf", config_name="self_loop")
def main(cfg: DictConfig) -> None:
    """CLI: headline numbers and where the outputs went."""
    # imported here: --help and a refused setting answer before torch loads
    from pinnmpc.simulation.self_loop import run_self_loop

    run_job(lambda run_dir: run_self_loop(cfg, run_dir), "pinnmpc.self_loop", _summary)


def _summary(m: dict[str, Any], run_dir: Path) -> str:
    """One line: MAE per state against the plant."""
    mae = ", ".join(f"{k} {v:.2e}" for k, v in m["mae"].items())
    return f"self-loop {m['steps']} steps, MAE vs plant: {mae}; outputs in {run_dir}"


if __name__ == "__main__":
    check_choices("pinnmpc.self_loop")
    main()
