"""The identified arm as a system config: conf/system/<arm>.yaml's structure with the fitted dynamics values, and
run_identify, the job `python -m pinnmpc.identify` runs (read the logs, fit, write that config). The config never
replaces a file unless overwrite=true, and never goes into the project's conf/ or the package (the shipped configs)."""

from __future__ import annotations

import copy
import json
import logging
import re
import time
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf

from pinnmpc.robot_data.checks import cut_short_note
from pinnmpc.robot_data.identify import Fit, identify, residual_fraction
from pinnmpc.robot_data.logs import read_logs
from pinnmpc.robot_data.settings import validate_identify
from pinnmpc.systems.registry import load_system
from pinnmpc.systems.settings import job_system
from pinnmpc.systems.urdf import Payload, RigidArm, portable_urdf
from pinnmpc.util.io import atomic_create, atomic_write, save_json
from pinnmpc.util.paths import CONF, PACKAGE  # never written: conf/ and the installed package

log = logging.getLogger(__name__)

NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def system_name(name: str | None, out: str | None, nominal: str) -> str:
    """The fitted system's name: given, else the output file's stem, else <nominal>_identified; checked here so a
    bad one fails before the fit."""
    chosen = name or (Path(out).stem if out else f"{nominal}_identified")
    if not NAME.fullmatch(chosen):
        key = "name" if name else "out"
        raise ValueError(
            f"{key}={name or out!r} gives the system name {chosen!r}; expected letters, digits and _ only, not "
            "starting with a digit (it names the compiled C functions)"
        )
    return chosen


def _round(values: list[float]) -> list[float]:
    """Numbers as written: 6 significant digits are far below what the fit resolves."""
    return [float(f"{v:.6g}") for v in values]


def system_yaml(
    nominal: dict[str, Any], fit: Fit, logs_meta: list[dict[str, Any]], logs: list[str], notes: list[str] | None = None
) -> str:
    """The nominal system's config (as composed) with the fitted dynamics (name, friction or servo gain, payload,
    armature), a comment header with the fit's residuals and the logs' meta, and `identified_from` naming it (and
    the warnings its logs gave, notes)."""
    cfg = copy.deepcopy(nominal)
    dyn, arm = cfg["dynamics"], fit.system
    nominal_name = dyn["name"]
    dyn["name"] = arm.name
    dyn["joint_prefix"] = f"{nominal_name}_" if dyn.get("joint_prefix") is None else dyn["joint_prefix"]  # its names
    dyn["urdf"] = portable_urdf(dyn["urdf"])
    for key in ("viscous", "coulomb", "servo_gain"):
        if key in dyn or key in fit.fitted:
            dyn[key] = _round(list(getattr(arm, key)))
    for key in ("payload", "load"):
        mass = getattr(arm, key)
        dyn[key] = None if mass is None else {
            "mass": _round([mass.mass])[0],
            "pos": None if mass.pos is None else _round(list(mass.pos)),
            "link": mass.link,
        }  # fmt: skip
    dyn["armature"] = _round(list(arm.armature)) if arm.armature else None
    cfg["identified_from"] = {
        "system": nominal_name,
        "logs": logs,
        "fitted": list(fit.fitted),
        "torque_rms": _round(fit.torque_rms),
        "prediction_rmse": _round(fit.prediction_rmse),
    }
    if notes:
        cfg["identified_from"]["warnings"] = list(notes)
    fmt = lambda v: "[" + ", ".join(f"{x:.3g}" for x in v) + "]"  # noqa: E731
    header = [
        f"# {arm.name}: {nominal_name} identified by pinnmpc.identify (bounded least squares on {fit.samples} joint",
        "# equations over fine intervals; pinnmpc/robot_data/identify.py). Fitted: " + ", ".join(fit.fitted) + ".",
        f"# Interval-mean torque residual RMS per joint {fmt(fit.torque_rms)} N m (the nominal model's "
        f"{fmt(fit.nominal_torque_rms)});",
        f"# one-period RK4 prediction RMSE per state {fmt(fit.prediction_rmse)} (the nominal model's "
        f"{fmt(fit.nominal_prediction_rmse)}).",
        "# `robots` are the nominal arm's: a plant of them should be built on identified_from.system, not on this",
        "# model (whose friction is the fit's).",
    ]
    for path, meta in zip(logs, logs_meta):
        keys = ("system", "robot", "robot_time_s", "fine", "noise_sigma", "seed", "created", "cut_short")
        keep = {k: meta.get(k) for k in keys}
        header.append(f"# log {path}: {json.dumps(keep)}")
        header.append(f"#   command: {meta.get('command')}")
    return "\n".join(header) + "\n" + OmegaConf.to_yaml(OmegaConf.create(cfg))


def write_system(path: str | Path, text: str, overwrite: bool = False) -> Path:
    """The system .yaml, atomically; an existing file is replaced only with overwrite (else ValueError)."""
    try:
        return (atomic_write if overwrite else atomic_create)(path, lambda p: p.write_text(text, encoding="utf-8"))
    except FileExistsError:
        raise ValueError(f"out={path}: the file exists; expected a new path, or overwrite=true to replace it") from None


def check_out(out: Path, given: str | None, overwrite: bool) -> None:
    """Before the fit: the shipped configs and the package are never written, an existing file only on request."""
    key = f"out={given}" if given else f"out=null ({out})"
    if out.suffix not in (".yaml", ".yml"):
        raise ValueError(f"{key}; expected a .yaml file path (or null: the run dir)")
    target = out.resolve()
    for folder, what in ((CONF, "the project's conf/"), (PACKAGE, "the installed package")):
        if target == folder or folder in target.parents:
            raise ValueError(
                f"{key} lies inside {what} ({folder}); expected a path outside it (the shipped configs are never "
                "written: write elsewhere and use it with --config-dir <dir>)"
            )
    if target.exists() and not overwrite:
        raise ValueError(f"{key}: the file exists; expected a new path, or overwrite=true to replace it")


def _place(pos: Any) -> tuple[float, ...] | None:
    """A configured place (three numbers, m) as a tuple; null stays None."""
    return None if pos is None else tuple(float(v) for v in pos)


def run_identify(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Read and check the logs, fit, write the system .yaml (read back as a system) and fit.json."""
    start = time.perf_counter()
    system = job_system(cfg, validate_identify)
    if not isinstance(system, RigidArm):
        raise ValueError(f"system={system.name}: identify fits URDF arms (RigidArm); expected planar3, panda or such")
    nominal = cfg.system.dynamics.name
    name = system_name(cfg.name, cfg.out, nominal)
    out = Path(cfg.out) if cfg.out else run_dir / "system" / f"{name}.yaml"
    check_out(out, cfg.out, bool(cfg.overwrite))
    paths = [str(p) for p in cfg.logs]
    logs = read_logs(paths, system)
    notes = [n for n in (cut_short_note(lg, p) for lg, p in zip(logs, paths)) if n]
    pos = _place(cfg.payload.pos)
    load = None if cfg.load.pos is None and cfg.load.link is None else Payload(0.0, _place(cfg.load.pos), cfg.load.link)
    fit = identify(
        system,
        logs,
        [k for k, on in cfg.fit.items() if on],
        Payload(0.0, pos, cfg.payload.link),
        name=name,
        max_samples=cfg.max_samples,
        min_speed=float(cfg.min_speed),
        place_range=float(cfg.payload.range),
        validation_periods=int(cfg.validation_periods),
        rk4_steps=int(cfg.rk4_steps),
        seed=int(cfg.seed),
        settle=float(cfg.settle),
        load=load,
        command=str(cfg.command),
    )
    fraction = residual_fraction(system, fit)
    outside = max(fraction) > float(cfg.class_residual)
    if outside:
        worst = int(np.argmax(fraction))
        note = (
            f"the robot is outside the model's class: the fit leaves {fraction[worst]:.3g} of {system.joints[worst]}'s "
            f"torque scale unexplained (class_residual={cfg.class_residual:g}); effects no coefficient here expresses "
            "(Stribeck or load-dependent friction, motor droop, cogging, actuator lag) remain: fine-tune a network on "
            "the logs (docs/robot.md)"
        )
        log.warning("%s", note)
        notes.append(note)
    composed = OmegaConf.to_container(cfg.system, resolve=True)
    text = system_yaml(composed, fit, [lg.meta for lg in logs], paths, notes)
    write_system(out, text, bool(cfg.overwrite))
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
        "residual_fraction": fraction,
        "outside_class": outside,
        "robot_time_s": float(sum(lg.robot_time for lg in logs)),
        "warnings": notes,
        "wall_s": time.perf_counter() - start,
    }
    save_json(run_dir / "fit.json", result)
    return result
