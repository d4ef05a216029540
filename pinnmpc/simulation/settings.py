"""The settings of the closed-loop jobs (closed_loop, robustness, self_loop), checked before anything loads."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf, open_dict

from pinnmpc.plant.settings import plant_settings
from pinnmpc.systems.settings import system_dims
from pinnmpc.util import checks as c
from pinnmpc.util.checks import SEED, Check, SettingError

log = logging.getLogger(__name__)

CLOSED_LOOP: dict[str, Check] = {
    "checkpoint": c.optional(c.text()),
    "tau": c.optional(c.positive()),
    "threads": c.integer(1),
    "seed": SEED,
    "noise_sigma": c.real(0.0),
    "max_steps": c.optional(c.integer(1)),
    "x0": c.optional(c.vector("nx")),
    "progress": c.boolean(),
    "plots": c.boolean(),
    "animate": c.boolean(),
    "long_horizon": c.integer(1),
    "allow_inputs_outside_box": c.boolean(),
    "failure.max_fallback_fraction": c.real(0.0, 1.0),
    "reference.path": c.optional(c.text()),
    "reference.name": c.text(),
}  # the controller's settings are its kind's dataclass (controller/base.py), checked by validate_controller


ROBUSTNESS: dict[str, Check] = {
    **CLOSED_LOOP,
    "robustness.noise_sigma": c.listof(c.real(0.0)),
    "robustness.friction_scale": c.listof(c.real(0.0)),
    "robustness.mass_scale": c.listof(c.positive()),
    "robustness.bound": c.positive(),
}


SELF_LOOP: dict[str, Check] = {
    "checkpoint": c.optional(c.text()),
    "steps": c.integer(2),
    "amplitude": c.vector("nu"),
    "x0": c.vector("nx"),
    "threads": c.integer(1),
    "plots": c.boolean(),
}


def validate_closed_loop(cfg: DictConfig, system: Any, table: Mapping[str, Check] = CLOSED_LOOP) -> None:
    """closed_loop (and robustness) settings, before the surrogate is loaded."""
    c.validate(cfg, table, system_dims(system))
    validate_controller(cfg, system)
    validate_plant(cfg)


def validate_controller(cfg: DictConfig, system: Any) -> None:
    """The controller's settings by its registered kind's dataclass, before anything is built or loaded."""
    import pinnmpc.simulation.setup  # noqa: F401  (registers the built-in kinds)
    from pinnmpc.controller.registry import controller_settings

    controller_settings(cfg.controller, system)


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
    c.validate(cfg, SELF_LOOP, system_dims(system))


def within_plant_limits(cfg: DictConfig, system: Any) -> None:
    """controller.u_low/u_high narrowed to the plant's velocity limits where it has them (plant=franka: franky's,
    beyond which the safety layer clips each command), so that no plan counts on a command the robot never runs."""
    limit = OmegaConf.select(cfg, "plant.velocity_limit", default=None)
    if limit is None or "controller" not in cfg:
        return
    v = np.asarray(list(limit), dtype=float)  # each positive: validate_plant, before any job gets here
    nu = len(system.input_names)
    if v.shape != (nu,):
        raise SettingError(f"plant.velocity_limit={v.tolist()}: expected {nu} positive speeds, rad/s")
    box = system.input_box
    low = np.asarray(box.low if cfg.controller.get("u_low") is None else cfg.controller.u_low, dtype=float)
    high = np.asarray(box.high if cfg.controller.get("u_high") is None else cfg.controller.u_high, dtype=float)
    low2, high2 = np.maximum(low, -v), np.minimum(high, v)
    if np.array_equal(low2, low) and np.array_equal(high2, high):
        return
    log.info("controller input box narrowed to plant.velocity_limit: u_high %s", np.round(high2, 4).tolist())
    with open_dict(cfg.controller):
        cfg.controller.u_low, cfg.controller.u_high = low2.tolist(), high2.tolist()
