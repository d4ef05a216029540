"""`python -m pinnmpc.robustness`: closed loops under measurement noise and plant mismatch, one table."""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from pinnmpc.cli import check_choices, run_job


@hydra.main(version_base="1.3", config_path="../conf", config_name="robustness")
def main(cfg: DictConfig) -> None:
    """CLI: print the table."""
    # imported here: --help and a refused setting answer before torch loads
    from pinnmpc.simulation.robustness import run_robustness

    run_job(
        lambda run_dir: run_robustness(cfg, run_dir),
        "pinnmpc.robustness",
        lambda _rows, run_dir: (run_dir / "robustness.md").read_text() + f"outputs in {run_dir}",
    )


if __name__ == "__main__":
    check_choices("pinnmpc.robustness")
    main()
