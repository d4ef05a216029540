"""The identified arm as a system config: conf/system/<arm>.yaml's structure with the fitted dynamics values."""

from __future__ import annotations

import copy
import json
import re
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from pinnmpc.robot_data.identify import Fit
from pinnmpc.systems.urdf import portable_urdf
from pinnmpc.util.io import atomic_write

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


def system_yaml(nominal: dict[str, Any], fit: Fit, logs_meta: list[dict[str, Any]], logs: list[str]) -> str:
    """The nominal system's config (as composed) with the fitted dynamics (name, friction or servo gain, payload,
    armature), a comment header with the fit's residuals and the logs' meta, and `identified_from` naming it."""
    cfg = copy.deepcopy(nominal)
    dyn, arm = cfg["dynamics"], fit.system
    nominal_name = dyn["name"]
    dyn["name"] = arm.name
    dyn["joint_prefix"] = f"{nominal_name}_" if dyn.get("joint_prefix") is None else dyn["joint_prefix"]  # its names
    dyn["urdf"] = portable_urdf(dyn["urdf"])
    for key in ("viscous", "coulomb", "servo_gain"):
        if key in dyn or key in fit.fitted:
            dyn[key] = _round(list(getattr(arm, key)))
    payload = arm.payload
    dyn["payload"] = None if payload is None else {
        "mass": _round([payload.mass])[0],
        "pos": None if payload.pos is None else _round(list(payload.pos)),
        "link": payload.link,
    }  # fmt: skip
    dyn["armature"] = _round(list(arm.armature)) if arm.armature else None
    cfg["identified_from"] = {
        "system": nominal_name,
        "logs": logs,
        "fitted": list(fit.fitted),
        "torque_rms": _round(fit.torque_rms),
        "prediction_rmse": _round(fit.prediction_rmse),
    }
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
        keep = {k: meta.get(k) for k in ("system", "robot", "robot_time_s", "fine", "noise_sigma", "seed", "created")}
        header.append(f"# log {path}: {json.dumps(keep)}")
        header.append(f"#   command: {meta.get('command')}")
    return "\n".join(header) + "\n" + OmegaConf.to_yaml(OmegaConf.create(cfg))


def write_system(path: str | Path, text: str) -> Path:
    """The system .yaml, atomically."""
    return atomic_write(path, lambda p: p.write_text(text, encoding="utf-8"))
