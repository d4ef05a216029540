"""`python -m pinnmpc.identify logs=[...]`: the model's friction, payload and armature fitted to robot logs."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig

from pinnmpc.cli import check_choices, run_job


@hydra.main(version_base="1.3", config_path="../conf", config_name="identify")
def main(cfg: DictConfig) -> None:
    """CLI: one summary line with the fitted values and where the system went."""
    # imported here: --help and a refused setting answer before torch loads
    from pinnmpc.robot_data.identify_job import run_identify

    run_job(lambda run_dir: run_identify(cfg, run_dir), "pinnmpc.identify", _summary)


def _summary(m: dict[str, Any], run_dir: Path) -> str:
    """One line: the fitted values, the residuals against the nominal model's and the file."""
    import numpy as np  # here, not at the top: a command module imports only hydra, omegaconf and pinnmpc.cli

    fmt = lambda v: np.array2string(np.asarray(v, dtype=float), precision=4, separator=", ", max_line_width=10**6)  # noqa: E731
    v = m["values"]
    friction = (
        f"servo gain {fmt(v['servo_gain'])}" if "servo_gain" in m["fitted"]
        else f"viscous {fmt(v.get('viscous', []))}"
    )  # fmt: skip
    if "coulomb" in m["fitted"]:
        friction += f", coulomb {fmt(v['coulomb'])}"
    place = f" at [{', '.join(f'{c:.4f}' for c in v['payload_pos'])}] m" if "payload_pos" in v else ""
    return (
        f"identified {m['system']} from {m['robot_time_s']:.0f} s of robot time in {m['wall_s']:.1f} s: payload "
        f"{v['payload_mass']:.4g} kg{place}, armature {fmt(v['armature'])}, {friction}; torque residual RMS "
        f"{fmt(m['torque_rms'])} N m (nominal {fmt(m['nominal_torque_rms'])}); system in {m['out']}"
    )


if __name__ == "__main__":
    check_choices("pinnmpc.identify")
    main()
