"""The settings of the robot-data jobs (collect, identify), checked before a robot or a log is touched."""

from __future__ import annotations

from typing import Any

from omegaconf import DictConfig

from pinnmpc.simulation.settings import validate_plant
from pinnmpc.systems.settings import system_dims
from pinnmpc.util import checks as c
from pinnmpc.util.checks import SEED, Check, SettingError

COLLECT: dict[str, Check] = {  # conf/collect.yaml
    "robot_time": c.positive(),
    "fine": c.integer(1),
    "noise_sigma": c.real(0.0),
    "seed": c.integer(0, 2**31 // 1000 - 1),  # episode seeds are seed * 1000 + episode
    "checkpoint": c.optional(c.text()),
    "allow_inputs_outside_box": c.boolean(),
    "threads": c.integer(1),
    "progress": c.boolean(),
    "out": c.text(),
    "episodes.kinds": c.listof(c.one_of("random", "driven", "excitation")),
    "excitation.duration": c.positive(),
    "excitation.fraction": c.real(0.0, 1.0),
    "excitation.bandwidth": c.positive(),
    "excitation.damping": c.real(0.0),
    "excitation.amplitude": c.real(0.0, 1.0),
    "excitation.hold": c.integer(1),
    "excitation.target_every": c.positive(),
    "excitation.speed": c.real(0.0, 1.0),
    "controller.horizon": c.integer(1),
    "controller.Q": c.weight("nx"),
    "controller.R": c.weight("nu"),
    "controller.u_low": c.optional(c.vector("nu")),
    "controller.u_high": c.optional(c.vector("nu")),
}


IDENTIFY: dict[str, Check] = {  # conf/identify.yaml
    "class_residual": c.positive(),
    "logs": c.listof(c.text()),
    "out": c.optional(c.text()),
    "overwrite": c.boolean(),
    "name": c.optional(c.text()),
    "fit.viscous": c.boolean(),
    "fit.coulomb": c.boolean(),
    "fit.servo_gain": c.boolean(),
    "fit.payload": c.boolean(),
    "fit.payload_pos": c.boolean(),
    "fit.armature": c.boolean(),
    "fit.load": c.boolean(),
    "payload.pos": c.optional(c.vector(3)),
    "payload.range": c.positive(),
    "payload.link": c.optional(c.text()),
    "load.pos": c.optional(c.vector(3)),
    "load.link": c.optional(c.text()),
    "command": c.one_of("held", "reported"),
    "max_samples": c.optional(c.integer(1)),
    "min_speed": c.real(0.0),
    "settle": c.real(0.0),
    "validation_periods": c.integer(0),
    "rk4_steps": c.integer(1),
    "seed": SEED,
    "threads": c.integer(1),
}


def validate_collect(cfg: DictConfig, system: Any) -> None:
    """collect settings, before the robot or the controller is built."""
    c.validate(cfg, COLLECT, system_dims(system))
    c.pair(cfg, "controller.u_low", "controller.u_high")
    validate_plant(cfg)
    if cfg.plant.get("kind") == "mujoco" and int(cfg.plant.substeps) % int(cfg.fine):
        raise SettingError(
            f"plant.substeps={cfg.plant.substeps} is not a multiple of fine={cfg.fine}: expected a multiple, so the "
            "fine plant keeps the control-rate plant's RK4 step"
        )


def validate_identify(cfg: DictConfig, system: Any) -> None:
    """identify settings, before any log is read."""
    c.validate(cfg, IDENTIFY, system_dims(system))
    if not cfg.logs:
        raise SettingError("logs=[]: expected at least one robot log (.npz or .csv from pinnmpc.collect)")
