"""The settings of the training jobs (train, residuals, time_basis, capacity), checked before any data is drawn."""

from __future__ import annotations

from typing import Any

from omegaconf import DictConfig, OmegaConf

from pinnmpc.surrogate.prior import KINDS as PRIOR_KINDS
from pinnmpc.systems.settings import system_dims, validate_system
from pinnmpc.training.settings import section_settings
from pinnmpc.util import checks as c
from pinnmpc.util.checks import SEED, Check, SettingError

RESIDUALS: dict[str, Check] = {
    "checkpoint": c.optional(c.text()),
    "points": c.integer(1),
    "bins": c.integer(1),
    "seed": SEED,
    "threads": c.integer(1),
    "plots": c.boolean(),
}


TIME_BASIS: dict[str, Check] = {
    "t_max": c.positive(),
    "time_basis": c.listof(c.positive(), empty=True),
    "candidates": c.listof(c.positive(), empty=True),
    "greedy": c.integer(0),
    "degree": c.integer(0),
    "points": c.integer(1),
    "dt": c.positive(),
    "h": c.positive(),
    "seed": SEED,
    "threads": c.integer(1),
    "plots": c.boolean(),
    "near_target": c.positive(),
}


CAPACITY: dict[str, Check] = {
    "t_max": c.positive(),
    "points": c.integer(1),
    "val_points": c.integer(1),
    "h": c.positive(),
    "minutes": c.positive(),
    "max_steps": c.optional(c.integer(1)),
    "lbfgs.max_iter": c.integer(1),
    "lbfgs.history": c.integer(1),
    "give_up_after": c.integer(1),
    "seed": SEED,
    "threads": c.integer(1),
    "progress": c.boolean(),
    "plots": c.boolean(),
    "dtype": c.one_of("float32", "float64"),
    "model.hidden": c.listof(c.integer(1)),
    "model.prior": c.optional(c.one_of(*PRIOR_KINDS)),
}


TRAIN: dict[str, Check] = {
    "t_max": c.positive(),
    "seed": SEED,
    "threads": c.integer(0),  # 0: every available core (a GPU host evaluating a URDF arm's rhs)
    "ckpt_path": c.optional(c.text()),
    "resume": c.boolean(),
    "progress": c.boolean(),
    "self_loop_figure.every_n_epochs": c.integer(0),
    "self_loop_figure.steps": c.integer(2),
    "self_loop_figure.amplitude": c.vector("nu"),
    "init_from": c.optional(c.text()),
    "physics": c.optional(c.text()),
    "physics_prior_slope": c.optional(c.real(0.0)),
    "model.hidden": c.listof(c.integer(1)),  # before stage.hidden, which defaults to it
    "stage.base": c.optional(c.text()),
    "stage.hidden": c.listof(c.integer(1)),
    "stage.error_scale": c.positive(),
    "stage.first_layer_gain": c.positive(),
    "stage.last_layer_gain": c.real(0.0),  # 0: the stage starts exactly at the base network
    "stage.samples": c.integer(1),
    "stage.h": c.positive(),
    "model.prior": c.optional(c.one_of(*PRIOR_KINDS)),
    "model.previous_input": c.boolean(),
    "model.command_delay": c.optional(c.positive()),
    "module.anchor_state_weight": c.optional(
        c.vector("nx", c.positive())
    ),  # its length; the rest: validate_module_data
    "trainer.max_epochs": c.epochs(),
    "trainer.max_time": c.optional(c.duration()),
    "trainer.check_val_every_n_epoch": c.optional(c.integer(1)),
}


def validate_module_data(cfg: DictConfig) -> None:
    """The training's module and data settings by their own checks (pinnmpc/training/settings.py), in every job
    that trains."""
    for section in ("module", "data"):
        if section in cfg:
            try:
                section_settings(section, OmegaConf.to_container(cfg[section], resolve=True))
            except ValueError as e:
                raise SettingError(str(e)) from None


def validate_residuals(cfg: DictConfig, system: Any) -> None:
    """residuals settings: every t bin must hold a point, or its RMS would read 0."""
    c.validate(cfg, RESIDUALS, system_dims(system))
    if cfg.bins > cfg.points:
        raise SettingError(
            f"bins={cfg.bins} exceeds points={cfg.points}: expected bins <= points (each bin needs a point)"
        )


def _t_max_covers_tau(cfg: DictConfig, system: Any, why: str) -> None:
    """t_max below the control period would leave the one time the controller asks for outside the fitted range."""
    if cfg.t_max < system.tau:
        raise SettingError(f"t_max={cfg.t_max} is below the system's tau={system.tau}: expected t_max >= tau ({why})")


def validate_time_basis(cfg: DictConfig, system: Any) -> None:
    """time_basis settings."""
    c.validate(cfg, TIME_BASIS, system_dims(system))
    _t_max_covers_tau(cfg, system, "the misfit is at tau")


def validate_capacity(cfg: DictConfig, system: Any) -> None:
    """capacity settings."""
    c.validate(cfg, CAPACITY, system_dims(system))
    _t_max_covers_tau(cfg, system, "the fit is at tau")


def validate_train(cfg: DictConfig, system: Any) -> None:
    """train settings and the system's per-joint lists, before any data is drawn (a wrong list would show only in
    the closed loop that comes after the training)."""
    validate_system(cfg, system)
    c.validate(cfg, TRAIN, system_dims(system))
    validate_module_data(cfg)
    if cfg.get("init_from") and (cfg.stage.base or cfg.stage.get("split") is not None):
        raise SettingError(
            f"init_from={cfg.init_from} starts one network from a trained one; expected stage.base=null and "
            f"stage.split=null with it, got {cfg.stage.base} and {cfg.stage.get('split')}"
        )
    staged = cfg.stage.base or cfg.stage.get("split") is not None
    if staged and cfg.model.get("prior") is not None:  # before the base trains its share, not after
        raise SettingError(
            f"stage.split/stage.base with model.prior={cfg.model.prior}: a correction stage does not support a "
            "prior; expected system.network.prior=null with it"
        )
    if cfg.model.get("previous_input") and not cfg.data.get("logs"):
        raise SettingError(
            "model.previous_input=true with data.logs=[]: only a robot's logs say what the previous input does; "
            "expected data.logs=[<robot_log.npz>, ...]"
        )
    delay = cfg.model.get("command_delay")
    if delay is not None and (cfg.model.get("previous_input") or not delay < system.tau):
        raise SettingError(
            f"model.command_delay={delay} with model.previous_input={cfg.model.get('previous_input')}; expected a "
            f"delay below the period {system.tau} s and model.previous_input=false (the split flow takes u_prev)"
        )
    _t_max_covers_tau(cfg, system, "the network predicts x(tau)")
