"""`python -m pinnmpc.export`: the surrogate's flow map and its Jacobian as CasADi functions, C source or ONNX."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig

from pinnmpc.cli import check_choices, run_job


@hydra.main(version_base="1.3", config_path="../conf", config_name="export")
def main(cfg: DictConfig) -> None:
    """CLI: the max error per check and where the files went."""
    # imported here: --help and a refused setting answer before torch loads
    from pinnmpc.surrogate.export import run_export

    overrides = hydra.core.hydra_config.HydraConfig.get().overrides.task
    given = any(o.lstrip("+").startswith("system=") for o in overrides)  # the checkpoint must then be of that arm
    run_job(lambda run_dir: run_export(cfg, run_dir, system_given=given), "pinnmpc.export", _summary)


def _summary(m: dict[str, Any], run_dir: Path) -> str:
    """One line: format, errors against the torch network, the files."""
    errors = ", ".join(f"{k} {v:.1e}" for k, v in m["max_abs_error"].items())
    files = ", ".join(m["files"])
    return f"export {m['format']}: max abs error vs torch on {m['points']} points: {errors}; {files} in {m['out']}"


if __name__ == "__main__":
    check_choices("pinnmpc.export")
    main()
