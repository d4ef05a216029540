"""`python -m pinnmpc.closed_loop [overrides]`: NMPC on the surrogate tracks a reference on the RK45 plant."""

from __future__ import annotations

import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

from pinnmpc.cli import StopSignal, check_choices, run_cli, say
from pinnmpc.simulation.metrics import headline
from pinnmpc.simulation.run import run_closed_loop


@hydra.main(version_base="1.3", config_path="../conf", config_name="closed_loop")
def main(cfg: DictConfig) -> None:
    """CLI: print the headline numbers and where the outputs went."""
    run_dir = Path(hydra.core.hydra_config.HydraConfig.get().runtime.output_dir)
    with StopSignal() as stop:
        m = run_cli(lambda: run_closed_loop(cfg, run_dir, stop), "pinnmpc.closed_loop", run_dir)
    say(headline(m, run_dir), run_dir, "pinnmpc.closed_loop")
    if m["status"] == "interrupted":
        print(f"pinnmpc.closed_loop: interrupted by {stop.name} after {m['steps']} steps", file=sys.stderr)
        sys.exit(stop.exit_code)
    if m["status"] != "ok":
        sys.exit(1)


if __name__ == "__main__":
    check_choices("pinnmpc.closed_loop")
    main()
