"""`python -m pinnmpc.closed_loop [overrides]`: NMPC on the surrogate tracks a reference on the RK45 plant."""

from __future__ import annotations

import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

from pinnmpc.cli import StopSignal, check_choices, end_job, exit_stopped, run_cli, say


@hydra.main(version_base="1.3", config_path="../conf", config_name="closed_loop")
def main(cfg: DictConfig) -> None:
    """CLI: print the headline numbers and where the outputs went."""
    # imported here: --help and a refused setting answer before torch loads
    from pinnmpc.simulation.metrics import headline
    from pinnmpc.simulation.run import run_closed_loop

    run_dir = Path(hydra.core.hydra_config.HydraConfig.get().runtime.output_dir)
    prog = "pinnmpc.closed_loop"
    announce = lambda m: say(headline(m, run_dir), run_dir, prog)  # noqa: E731  (the log line, before metrics.json)
    with StopSignal() as stop:
        m = run_cli(lambda: run_closed_loop(cfg, run_dir, stop, announce), prog, run_dir)
    if m["status"] == "interrupted":
        print(f"{prog}: interrupted by {stop.name} after {m['steps']} steps", file=sys.stderr)
        exit_stopped(stop.exit_code, f"interrupted by {stop.name}", run_dir)
    if m["status"] != "ok":
        end_job(1, m["status"], run_dir)


if __name__ == "__main__":
    check_choices("pinnmpc.closed_loop")
    main()
