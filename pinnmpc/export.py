"""`python -m pinnmpc.export`: the surrogate's flow map and its Jacobian as CasADi functions, C source or ONNX."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig

from pinnmpc.cli import check_choices, run_job
from pinnmpc.surrogate.checkpoint import shipped
from pinnmpc.surrogate.export import Tolerances, export
from pinnmpc.systems.base import System
from pinnmpc.util.settings import job_system, validate_export


def run_export(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Export, check and write the files; the returned dict is the export.json written next to them."""
    system: System = job_system(cfg, validate_export)
    checkpoint = shipped(system.name) if cfg.checkpoint is None else Path(cfg.checkpoint)
    out = run_dir if cfg.out is None else Path(cfg.out)
    tol = cfg.tolerance
    return export(
        checkpoint, cfg.format, out, points=cfg.points, jacobian_points=cfg.jacobian_points, seed=cfg.seed,
        tolerances=Tolerances(tol.float64, tol.float32, tol.jacobian), compiler=cfg.compiler, opt=cfg.opt,
        opset=cfg.opset,
    )  # fmt: skip


@hydra.main(version_base="1.3", config_path="../conf", config_name="export")
def main(cfg: DictConfig) -> None:
    """CLI: the max error per check and where the files went."""
    run_job(lambda run_dir: run_export(cfg, run_dir), "pinnmpc.export", _summary)


def _summary(m: dict[str, Any], run_dir: Path) -> str:
    """One line: format, errors against the torch network, the files."""
    errors = ", ".join(f"{k} {v:.1e}" for k, v in m["max_abs_error"].items())
    files = ", ".join(m["files"])
    return f"export {m['format']}: max abs error vs torch on {m['points']} points: {errors}; {files} in {m['out']}"


if __name__ == "__main__":
    check_choices("pinnmpc.export")
    main()
