"""The export job's settings, checked before the network is loaded."""

from __future__ import annotations

from typing import Any

from omegaconf import DictConfig

from pinnmpc.systems.settings import system_dims
from pinnmpc.util.checks import (
    SEED,
    Check,
    integer,
    one_of,
    optional,
    positive,
    text,
    validate,
)

EXPORT: dict[str, Check] = {  # conf/export.yaml
    "checkpoint": optional(text()),
    "format": one_of("casadi", "c", "onnx"),
    "out": optional(text()),
    "points": integer(1),
    "jacobian_points": integer(1),
    "seed": SEED,
    "tolerance.float64": positive(),
    "tolerance.float32": positive(),
    "tolerance.jacobian": positive(),
    "compiler": text(),
    "opt": text(),
    "opset": integer(7),
    "threads": integer(1),
}


def validate_export(cfg: DictConfig, system: Any) -> None:
    """export settings, before the network is loaded."""
    validate(cfg, EXPORT, system_dims(system))
