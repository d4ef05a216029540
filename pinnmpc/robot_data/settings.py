"""The settings of the robot-data jobs (collect, identify), checked before a robot or a log is touched."""

from __future__ import annotations

from typing import Any

from omegaconf import DictConfig

from pinnmpc.simulation.settings import validate_plant
from pinnmpc.systems.settings import system_dims
from pinnmpc.util.checks import (
    SEED,
    Check,
    SettingError,
    boolean,
    integer,
    listof,
    one_of,
    optional,
    pair,
    positive,
    real,
    text,
    validate,
    vector,
    weight,
)

COLLECT: dict[str, Check] = {  # conf/collect.yaml
    "robot_time": positive(),
    "fine": integer(1),
    "noise_sigma": real(0.0),
    "seed": integer(0, 2**31 // 1000 - 1),  # episode seeds are seed * 1000 + episode
    "checkpoint": optional(text()),
    "allow_inputs_outside_box": boolean(),
    "threads": integer(1),
    "progress": boolean(),
    "out": text(),
    "episodes.kinds": listof(one_of("random", "driven", "excitation")),
    "excitation.duration": positive(),
    "excitation.fraction": real(0.0, 1.0),
    "excitation.bandwidth": positive(),
    "excitation.damping": real(0.0),
    "excitation.amplitude": real(0.0, 1.0),
    "excitation.hold": integer(1),
    "excitation.target_every": positive(),
    "excitation.speed": real(0.0, 1.0),
    "controller.horizon": integer(1),
    "controller.Q": weight("nx"),
    "controller.R": weight("nu"),
    "controller.u_low": optional(vector("nu")),
    "controller.u_high": optional(vector("nu")),
}


IDENTIFY: dict[str, Check] = {  # conf/identify.yaml
    "logs": listof(text()),
    "out": optional(text()),
    "overwrite": boolean(),
    "name": optional(text()),
    "fit.viscous": boolean(),
    "fit.coulomb": boolean(),
    "fit.servo_gain": boolean(),
    "fit.payload": boolean(),
    "fit.payload_pos": boolean(),
    "fit.armature": boolean(),
    "payload.pos": optional(vector(3)),
    "payload.range": positive(),
    "payload.link": optional(text()),
    "max_samples": optional(integer(1)),
    "min_speed": real(0.0),
    "validation_periods": integer(0),
    "rk4_steps": integer(1),
    "seed": SEED,
    "threads": integer(1),
}


def validate_collect(cfg: DictConfig, system: Any) -> None:
    """collect settings, before the robot or the controller is built."""
    validate(cfg, COLLECT, system_dims(system))
    pair(cfg, "controller.u_low", "controller.u_high")
    validate_plant(cfg)
    if cfg.plant.get("kind") == "mujoco" and int(cfg.plant.substeps) % int(cfg.fine):
        raise SettingError(
            f"plant.substeps={cfg.plant.substeps} is not a multiple of fine={cfg.fine}: expected a multiple, so the "
            "fine plant keeps the control-rate plant's RK4 step"
        )


def validate_identify(cfg: DictConfig, system: Any) -> None:
    """identify settings, before any log is read."""
    validate(cfg, IDENTIFY, system_dims(system))
    if not cfg.logs:
        raise SettingError("logs=[]: expected at least one robot log (.npz or .csv from pinnmpc.collect)")
