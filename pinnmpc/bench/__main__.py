"""`python -m pinnmpc.bench [overrides]`: the thin Hydra entry over run_bench."""

from __future__ import annotations

from pathlib import Path

import hydra
from omegaconf import DictConfig

from pinnmpc.cli import check_choices, run_cli


@hydra.main(version_base="1.3", config_path="../../conf", config_name="bench")
def main(cfg: DictConfig) -> None:
    """CLI: run the benchmark and print its markdown."""
    # imported here: --help and a refused setting answer before torch loads
    from pinnmpc.bench.run import run_bench

    run_dir = Path(hydra.core.hydra_config.HydraConfig.get().runtime.output_dir)
    run_cli(lambda: run_bench(cfg, run_dir), "pinnmpc.bench", run_dir)
    print((run_dir / "bench.md").read_text())
    print(f"outputs in {run_dir}")


if __name__ == "__main__":
    check_choices("pinnmpc.bench")
    main()
