"""`python -m pinnmpc.collect`: run the (simulated) robot for a given robot time and write its log."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig

from pinnmpc.cli import StopSignal, check_choices, exit_stopped, run_cli, say


@hydra.main(version_base="1.3", config_path="../conf", config_name="collect")
def main(cfg: DictConfig) -> None:
    """CLI: one summary line, kept in the run dir's log."""
    # imported here: --help and a refused setting answer before torch loads
    from pinnmpc.robot_data.collect import run_collect

    run_dir = Path(hydra.core.hydra_config.HydraConfig.get().runtime.output_dir)
    with StopSignal() as stop:
        m = run_cli(lambda: run_collect(cfg, run_dir, stop), "pinnmpc.collect", run_dir)
    say(_summary(m), run_dir, "pinnmpc.collect")
    if m["interrupted"]:
        exit_stopped(stop.exit_code, f"interrupted by {stop.name}", run_dir)


def _summary(m: dict[str, Any]) -> str:
    """One line: how much was logged, how long it took and where it went; a log cut short says so first."""
    if not m["files"]:
        return f"collect cut short ({m['cut_short']}) in {m['wall_s']:.1f} s; no log written"
    head = f"collect cut short ({m['cut_short']}): " if m["cut_short"] else ""
    return (
        f"{head}collected {m['robot_time_s']:.1f} s of robot time in {m['episodes']} episodes ({m['samples']} samples, "
        f"{m['fine_samples']} fine) in {m['wall_s']:.1f} s; log in {m['files'][0]}"
    )


if __name__ == "__main__":
    check_choices("pinnmpc.collect")
    main()
