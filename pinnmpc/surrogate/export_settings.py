"""The export job's settings, checked before the network is loaded."""

from __future__ import annotations

from typing import Any

from omegaconf import DictConfig

from pinnmpc.systems.settings import system_dims
from pinnmpc.util import checks as c
from pinnmpc.util.checks import SEED, Check

EXPORT: dict[str, Check] = {  # conf/export.yaml
    "checkpoint": c.optional(c.text()),
    "format": c.one_of("casadi", "c", "onnx"),
    "out": c.optional(c.text()),
    "points": c.integer(1),
    "jacobian_points": c.integer(1),
    "seed": SEED,
    "tolerance.float64": c.positive(),
    "tolerance.float32": c.positive(),
    "tolerance.jacobian": c.positive(),
    "compiler": c.text(),
    "opt": c.text(),
    "opset": c.integer(7),
    "threads": c.integer(1),
}


def validate_export(cfg: DictConfig, system: Any) -> None:
    """export settings, before the network is loaded."""
    c.validate(cfg, EXPORT, system_dims(system))
