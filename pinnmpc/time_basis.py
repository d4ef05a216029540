"""`python -m pinnmpc.time_basis`: can the time gates span the flow's time dependence? (pinnmpc.training.time_basis)"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig

from pinnmpc.cli import check_choices, run_job


def _summary(m: dict[str, Any], run_dir: Path) -> str:
    """Two lines: the basis's misfit over the step, and the greedy basis's."""

    def line(entry: dict[str, Any]) -> str:
        return ", ".join(f"{k} {v:.2e}" for k, v in zip(m["state_names"], entry["rms"]))

    text = f"RMS gate misfit over [0, t_max] with time_basis={m['basis']['time_basis']}: {line(m['basis'])}"
    if m["greedy"]:
        text += f"\n  with time_basis={m['greedy'][-1]['time_basis']}: {line(m['greedy'][-1])}"
    return f"{text}\n{_verdict(m)}outputs in {run_dir}"


def _verdict(m: dict[str, Any]) -> str:
    """Against the one-step targets: the states whose misfit comes near them, where more gates would help."""
    targets, near = m.get("targets"), m.get("near_target")
    if not targets or near is None:
        return ""
    close = [
        f"{name} {v:.1e} (target {t:.0e})"
        for name, v, t in zip(m["state_names"], m["basis"]["rms"], targets)
        if t is not None and v > near * t
    ]
    if not close:
        return f"  every state's misfit is below {near:g}x its one-step target (system.targets.one_step_rmse)\n"
    hint = " (the line above tries some)" if m["greedy"] else ""
    return f"  above {near:g}x the one-step target: {', '.join(close)}; add gates there{hint}\n"


@hydra.main(version_base="1.3", config_path="../conf", config_name="time_basis")
def main(cfg: DictConfig) -> None:
    """CLI: the misfit of the basis and of its best extension, and where the outputs went."""
    # imported here: --help and a refused setting answer before torch loads
    from pinnmpc.training.time_basis import run_time_basis

    run_job(lambda run_dir: run_time_basis(cfg, run_dir), "pinnmpc.time_basis", _summary)


if __name__ == "__main__":
    check_choices("pinnmpc.time_basis")
    main()
