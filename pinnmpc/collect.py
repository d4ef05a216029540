"""`python -m pinnmpc.collect`: run the (simulated) robot for a given robot time and write its log."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf

from pinnmpc.cli import StopSignal, check_choices, exit_stopped, run_cli, say
from pinnmpc.robot_data.collect import collect
from pinnmpc.robot_data.logs import write_log
from pinnmpc.simulation.setup import build_controller, system_reference
from pinnmpc.util.settings import job_system, validate_collect


def run_collect(cfg: DictConfig, run_dir: Path, stop: StopSignal | None = None) -> dict[str, Any]:
    """Check the settings, build the robot first (a bad robot fails before the controller loads), collect, write."""
    from pinnmpc.robot_data.collect import fine_plant

    start = time.perf_counter()
    system = job_system(cfg, validate_collect)
    fine_plant(system, cfg.plant, int(cfg.fine), cfg.system.get("robots"))  # refuses an unknown or bad robot
    controller, _, tau = build_controller(cfg, system)
    if abs(tau - system.tau) > 1e-12 * system.tau:
        raise ValueError(f"the controller's tau={tau} differs from system.tau={system.tau}; expected one period")

    def reference(name: str) -> Any:
        """A built-in reference of the system by name."""
        return system_reference(OmegaConf.merge(cfg, {"reference": {"name": name, "path": None}}), system, tau)

    plant = OmegaConf.to_container(cfg.plant, resolve=True)
    robots = OmegaConf.to_container(cfg.system.get("robots") or {}, resolve=True)
    meta = {
        "robot": cfg.plant.get("robot"),
        "robot_effects": robots.get(cfg.plant.get("robot")) if cfg.plant.get("robot") else None,
        "seed": int(cfg.seed),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "command": " ".join(["python -m pinnmpc.collect", *sys.argv[1:]]),
        "sources": {"plant": plant, "controller": cfg.controller.get("kind", "pinn"), "checkpoint": cfg.checkpoint,
                    "episodes": list(cfg.episodes.kinds), "excitation": OmegaConf.to_container(cfg.excitation)},
    }  # fmt: skip
    log = collect(
        cfg, system, controller, reference, stop=None if stop is None else (lambda: stop.requested), meta=meta
    )
    files = write_log(run_dir / str(cfg.out), log)
    return {
        "robot_time_s": log.meta["robot_time_s"],
        "episodes": len(log.episodes),
        "samples": len(log.t),
        "fine_samples": len(log.t_fine),
        "wall_s": time.perf_counter() - start,
        "files": [str(f) for f in files],
        "interrupted": bool(stop is not None and stop.requested),
    }


@hydra.main(version_base="1.3", config_path="../conf", config_name="collect")
def main(cfg: DictConfig) -> None:
    """CLI: one summary line, kept in the run dir's log."""
    run_dir = Path(hydra.core.hydra_config.HydraConfig.get().runtime.output_dir)
    with StopSignal() as stop:
        m = run_cli(lambda: run_collect(cfg, run_dir, stop), "pinnmpc.collect", run_dir)
    say(_summary(m), run_dir, "pinnmpc.collect")
    if m["interrupted"]:
        exit_stopped(stop.exit_code, f"interrupted by {stop.name}", run_dir)


def _summary(m: dict[str, Any]) -> str:
    """One line: how much was logged, how long it took and where it went."""
    return (
        f"collected {m['robot_time_s']:.1f} s of robot time in {m['episodes']} episodes ({m['samples']} samples, "
        f"{m['fine_samples']} fine) in {m['wall_s']:.1f} s; log in {m['files'][0]}"
    )


if __name__ == "__main__":
    check_choices("pinnmpc.collect")
    main()
