"""`python -m pinnmpc.identify logs=[...]`: the model's friction, payload and armature fitted to robot logs."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import hydra
import numpy as np
from omegaconf import DictConfig, OmegaConf

from pinnmpc.cli import check_choices, run_job
from pinnmpc.robot_data.export import system_name, system_yaml, write_system
from pinnmpc.robot_data.identify import identify
from pinnmpc.robot_data.logs import read_logs
from pinnmpc.systems.registry import load_system
from pinnmpc.systems.urdf import Payload, RigidArm
from pinnmpc.util.io import save_json
from pinnmpc.util.settings import job_system, validate_identify


def run_identify(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Read and check the logs, fit, write the system .yaml (read back as a system) and fit.json."""
    start = time.perf_counter()
    system = job_system(cfg, validate_identify)
    if not isinstance(system, RigidArm):
        raise ValueError(f"system={system.name}: identify fits URDF arms (RigidArm); expected planar3, panda or such")
    nominal = cfg.system.dynamics.name
    name = system_name(cfg.name, cfg.out, nominal)
    out = Path(cfg.out) if cfg.out else run_dir / "system" / f"{name}.yaml"
    if out.suffix not in (".yaml", ".yml"):
        raise ValueError(f"out={cfg.out!r}; expected a .yaml file path (or null: the run dir)")
    logs = read_logs([str(p) for p in cfg.logs], system)
    pos = None if cfg.payload.pos is None else tuple(float(v) for v in cfg.payload.pos)
    fit = identify(
        system,
        logs,
        [k for k, on in cfg.fit.items() if on],
        Payload(0.0, pos, cfg.payload.link),
        name=name,
        max_samples=cfg.max_samples,
        min_speed=float(cfg.min_speed),
        validation_periods=int(cfg.validation_periods),
        rk4_steps=int(cfg.rk4_steps),
        seed=int(cfg.seed),
    )
    composed = OmegaConf.to_container(cfg.system, resolve=True)
    text = system_yaml(composed, fit, [lg.meta for lg in logs], [str(p) for p in cfg.logs])
    write_system(out, text)
    load_system(out)  # what closed_loop will build from it
    result = {
        "system": name,
        "out": str(out),
        "values": fit.values,
        "fitted": fit.fitted,
        "samples": fit.samples,
        "torque_rms": fit.torque_rms,
        "nominal_torque_rms": fit.nominal_torque_rms,
        "prediction_rmse": fit.prediction_rmse,
        "nominal_prediction_rmse": fit.nominal_prediction_rmse,
        "robot_time_s": float(sum(lg.robot_time for lg in logs)),
        "wall_s": time.perf_counter() - start,
    }
    save_json(run_dir / "fit.json", result)
    return result


@hydra.main(version_base="1.3", config_path="../conf", config_name="identify")
def main(cfg: DictConfig) -> None:
    """CLI: one summary line with the fitted values and where the system went."""
    run_job(lambda run_dir: run_identify(cfg, run_dir), "pinnmpc.identify", _summary)


def _summary(m: dict[str, Any], run_dir: Path) -> str:
    """One line: the fitted values, the residuals against the nominal model's and the file."""
    fmt = lambda v: np.array2string(np.asarray(v, dtype=float), precision=4, separator=", ", max_line_width=10**6)  # noqa: E731
    v = m["values"]
    friction = (
        f"servo gain {fmt(v['servo_gain'])}" if "servo_gain" in m["fitted"]
        else f"viscous {fmt(v.get('viscous', []))}, coulomb {fmt(v.get('coulomb', []))}"
    )  # fmt: skip
    return (
        f"identified {m['system']} from {m['robot_time_s']:.0f} s of robot time in {m['wall_s']:.1f} s: payload "
        f"{v['payload_mass']:.4g} kg, armature {fmt(v['armature'])}, {friction}; torque residual RMS "
        f"{fmt(m['torque_rms'])} N m (nominal {fmt(m['nominal_torque_rms'])}); system in {m['out']}"
    )


if __name__ == "__main__":
    check_choices("pinnmpc.identify")
    main()
