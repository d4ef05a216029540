"""The settings of the closed-loop jobs (closed_loop, robustness, self_loop), checked before anything loads."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from omegaconf import DictConfig, OmegaConf

from pinnmpc.plant.settings import plant_settings
from pinnmpc.systems.settings import system_dims
from pinnmpc.util.checks import (
    SEED,
    Check,
    SettingError,
    boolean,
    integer,
    listof,
    optional,
    pair,
    positive,
    real,
    text,
    validate,
    vector,
    weight,
)

CLOSED_LOOP: dict[str, Check] = {
    "checkpoint": optional(text()),
    "tau": optional(positive()),
    "threads": integer(1),
    "seed": SEED,
    "noise_sigma": real(0.0),
    "max_steps": optional(integer(1)),
    "x0": optional(vector("nx")),
    "progress": boolean(),
    "plots": boolean(),
    "animate": boolean(),
    "long_horizon": integer(1),
    "allow_inputs_outside_box": boolean(),
    "failure.max_fallback_fraction": real(0.0, 1.0),
    "reference.path": optional(text()),
    "reference.name": text(),
    # the keys every controller kind shares; the rest is each controller's own to check
    "controller.horizon": integer(1),
    "controller.Q": weight("nx"),
    "controller.R": weight("nu"),
    "controller.u_low": optional(vector("nu")),
    "controller.u_high": optional(vector("nu")),
}


ROBUSTNESS: dict[str, Check] = {
    **CLOSED_LOOP,
    "robustness.noise_sigma": listof(real(0.0)),
    "robustness.friction_scale": listof(real(0.0)),
    "robustness.mass_scale": listof(positive()),
    "robustness.bound": positive(),
}


SELF_LOOP: dict[str, Check] = {
    "checkpoint": optional(text()),
    "steps": integer(2),
    "amplitude": vector("nu"),
    "x0": vector("nx"),
    "threads": integer(1),
    "plots": boolean(),
}


def validate_closed_loop(cfg: DictConfig, system: Any, table: Mapping[str, Check] = CLOSED_LOOP) -> None:
    """closed_loop (and robustness) settings, before the surrogate is loaded."""
    validate(cfg, table, system_dims(system))
    pair(cfg, "controller.u_low", "controller.u_high")
    validate_plant(cfg)


def validate_plant(cfg: DictConfig) -> None:
    """The plant's settings by their own checks (pinnmpc/plant/settings.py), in every job that simulates one."""
    if "plant" in cfg:
        try:
            plant_settings(OmegaConf.to_container(cfg.plant, resolve=True))
        except ValueError as e:
            raise SettingError(str(e)) from None


def validate_robustness(cfg: DictConfig, system: Any) -> None:
    """The closed-loop settings plus the grid."""
    validate_closed_loop(cfg, system, ROBUSTNESS)


def validate_self_loop(cfg: DictConfig, system: Any) -> None:
    """self_loop settings."""
    validate(cfg, SELF_LOOP, system_dims(system))
