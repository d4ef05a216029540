"""Validated settings: every key a user passes is checked before any work starts, so a typo is one clear line."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from omegaconf import DictConfig, OmegaConf

from pinnmpc.plant.settings import plant_settings
from pinnmpc.surrogate.prior import KINDS as PRIOR_KINDS
from pinnmpc.training.settings import section_settings
from pinnmpc.util.checks import (  # noqa: F401 (SettingError re-exported: every job's setting error)
    _ABSENT,
    Check,
    Dims,
    SettingError,
    boolean,
    duration,
    epochs,
    integer,
    joint_index,
    listof,
    one_of,
    optional,
    per_state_targets,
    positive,
    real,
    text,
    vector,
    weight,
)

SEED = integer(0, 2**32 - 1)  # what numpy and Lightning accept

SYSTEM: dict[str, Check] = {  # the per-joint lists of conf/system/<name>.yaml that only some jobs read
    "system.network.periodic": listof(joint_index(), empty=True),
    "system.network.angle_sums": listof(listof(joint_index()), empty=True),
    "system.targets.one_step_rmse": per_state_targets(),
    "system.targets.closed_loop_mae": per_state_targets(),
    "system.self_loop.x0": vector("nx"),
    "system.self_loop.amplitude": vector("nu"),
    "system.control.Q": weight("nx"),  # the NMPC's weights: checked before a training the controller comes after
    "system.control.R": weight("nu"),
    "system.control.disturbance_max": optional(vector("nx", real(0.0))),
    "system.control.rti_trust": optional(positive()),
}

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

RESIDUALS: dict[str, Check] = {
    "checkpoint": optional(text()),
    "points": integer(1),
    "bins": integer(1),
    "seed": SEED,
    "threads": integer(1),
    "plots": boolean(),
}

TIME_BASIS: dict[str, Check] = {
    "t_max": positive(),
    "time_basis": listof(positive(), empty=True),
    "candidates": listof(positive(), empty=True),
    "greedy": integer(0),
    "degree": integer(0),
    "points": integer(1),
    "dt": positive(),
    "h": positive(),
    "seed": SEED,
    "threads": integer(1),
    "plots": boolean(),
    "near_target": positive(),
}

CAPACITY: dict[str, Check] = {
    "t_max": positive(),
    "points": integer(1),
    "val_points": integer(1),
    "h": positive(),
    "minutes": positive(),
    "max_steps": optional(integer(1)),
    "lbfgs.max_iter": integer(1),
    "lbfgs.history": integer(1),
    "give_up_after": integer(1),
    "seed": SEED,
    "threads": integer(1),
    "progress": boolean(),
    "plots": boolean(),
    "dtype": one_of("float32", "float64"),
    "model.hidden": listof(integer(1)),
    "model.prior": optional(one_of(*PRIOR_KINDS)),
}

TRAIN: dict[str, Check] = {
    "t_max": positive(),
    "seed": SEED,
    "threads": integer(0),  # 0: every available core (a GPU host evaluating a URDF arm's rhs)
    "ckpt_path": optional(text()),
    "resume": boolean(),
    "progress": boolean(),
    "self_loop_figure.every_n_epochs": integer(0),
    "self_loop_figure.steps": integer(2),
    "self_loop_figure.amplitude": vector("nu"),
    "init_from": optional(text()),
    "physics": optional(text()),
    "physics_prior_slope": optional(real(0.0)),
    "model.hidden": listof(integer(1)),  # before stage.hidden, which defaults to it
    "stage.base": optional(text()),
    "stage.hidden": listof(integer(1)),
    "stage.error_scale": positive(),
    "stage.first_layer_gain": positive(),
    "stage.last_layer_gain": real(0.0),  # 0: the stage starts exactly at the base network
    "stage.samples": integer(1),
    "stage.h": positive(),
    "model.prior": optional(one_of(*PRIOR_KINDS)),
    "module.anchor_state_weight": optional(vector("nx", positive())),  # its length; the rest: validate_module_data
    "trainer.max_epochs": epochs(),
    "trainer.max_time": optional(duration()),
    "trainer.check_val_every_n_epoch": optional(integer(1)),
}

BENCH: dict[str, Check] = {  # the sizes of its sections (a zero or empty one failed deep inside a section)
    "threads": integer(1),
    "seed": SEED,
    "failure.max_fallback_fraction": real(0.0, 1.0),
    "step.batch_sizes": listof(integer(1)),
    "step.n_states": integer(1),
    "step.repeats": integer(1),
    "step.warmup": integer(0),
    "step.rk45_loop_repeats": integer(1),
    "closed_loop.max_steps": optional(integer(1)),
    "robot.references": listof(text()),
    "robot.adapted": optional(text()),
    "robot.identified": optional(text()),
    "robot.logs": optional(listof(text())),
    "robot.rk4_steps": integer(1),
    "optimality.n_states": integer(1),
    "optimality.random_starts": integer(0),
    "scaling.horizons": listof(integer(1)),
    "scaling.batch_sizes": listof(integer(1)),
    "scaling.base_batch": integer(1),
    "scaling.base_horizon": optional(integer(1)),
    "scaling.repeats": integer(1),
    "scaling.warmup": integer(0),
    "scaling.step_batch_sizes": listof(integer(1)),
    "scaling.step_repeats": integer(1),
    "scaling.step_warmup": integer(0),
}
BENCH_SECTIONS = ("step", "closed_loop", "optimality", "scaling", "classical", "robot")

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


def _plain(value: Any) -> Any:
    """Config nodes as plain lists/dicts, for the checks and the messages."""
    if OmegaConf.is_config(value):
        return OmegaConf.to_container(value, resolve=True)
    return value


def validate(cfg: DictConfig, table: Mapping[str, Check], dims: Dims) -> None:
    """Check every key of table that cfg has; the first bad one raises SettingError naming key, value, allowed."""
    for key, check in table.items():
        value = _plain(OmegaConf.select(cfg, key, default=_ABSENT))
        if value is _ABSENT:
            continue
        allowed = check(value, dims)
        if allowed is not None:
            raise SettingError(f"{key}={value!r}: expected {allowed}")


def _pair(cfg: DictConfig, low_key: str, high_key: str) -> None:
    """low <= high entry by entry, when both are given."""
    low, high = (_plain(OmegaConf.select(cfg, k, default=None)) for k in (low_key, high_key))
    if low is not None and high is not None and any(lo > hi for lo, hi in zip(low, high)):
        raise SettingError(f"{low_key}={low} exceeds {high_key}={high}: expected low <= high in every entry")


def validate_system(cfg: DictConfig, system: Any) -> None:
    """The system config's per-joint lists against the arm its URDF builds, for every job (a new arm's config)."""
    validate(cfg, SYSTEM, system_dims(system))


def system_dims(system: Any) -> dict[str, int]:
    """nx and nu of a System (or anything with state and input names)."""
    return {"nx": len(system.state_names), "nu": len(system.input_names)}


def validate_closed_loop(cfg: DictConfig, system: Any, table: Mapping[str, Check] = CLOSED_LOOP) -> None:
    """closed_loop (and robustness) settings, before the surrogate is loaded."""
    validate(cfg, table, system_dims(system))
    _pair(cfg, "controller.u_low", "controller.u_high")
    validate_plant(cfg)


def validate_plant(cfg: DictConfig) -> None:
    """The plant's settings by their own checks (pinnmpc/plant/settings.py), in every job that simulates one."""
    if "plant" in cfg:
        try:
            plant_settings(OmegaConf.to_container(cfg.plant, resolve=True))
        except ValueError as e:
            raise SettingError(str(e)) from None


def validate_module_data(cfg: DictConfig) -> None:
    """The training's module and data settings by their own checks (pinnmpc/training/settings.py), in every job
    that trains."""
    for section in ("module", "data"):
        if section in cfg:
            try:
                section_settings(section, OmegaConf.to_container(cfg[section], resolve=True))
            except ValueError as e:
                raise SettingError(str(e)) from None


def validate_robustness(cfg: DictConfig, system: Any) -> None:
    """The closed-loop settings plus the grid."""
    validate_closed_loop(cfg, system, ROBUSTNESS)


def validate_self_loop(cfg: DictConfig, system: Any) -> None:
    """self_loop settings."""
    validate(cfg, SELF_LOOP, system_dims(system))


def validate_residuals(cfg: DictConfig, system: Any) -> None:
    """residuals settings: every t bin must hold a point, or its RMS would read 0."""
    validate(cfg, RESIDUALS, system_dims(system))
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
    validate(cfg, TIME_BASIS, system_dims(system))
    _t_max_covers_tau(cfg, system, "the misfit is at tau")


def validate_capacity(cfg: DictConfig, system: Any) -> None:
    """capacity settings."""
    validate(cfg, CAPACITY, system_dims(system))
    _t_max_covers_tau(cfg, system, "the fit is at tau")


def validate_train(cfg: DictConfig, system: Any) -> None:
    """train settings and the system's per-joint lists, before any data is drawn (a wrong list would show only in
    the closed loop that comes after the training)."""
    validate_system(cfg, system)
    validate(cfg, TRAIN, system_dims(system))
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
    _t_max_covers_tau(cfg, system, "the network predicts x(tau)")


def validate_bench(cfg: DictConfig, system: Any) -> None:
    """bench settings: the sections' sizes, and at least one section to run."""
    validate(cfg, BENCH, system_dims(system))
    validate_plant(cfg)
    if not any(OmegaConf.select(cfg, f"{name}.enabled", default=False) for name in BENCH_SECTIONS):
        keys = ", ".join(f"{name}.enabled" for name in BENCH_SECTIONS)
        raise SettingError(f"every bench section is off ({keys} all false); expected at least one enabled")


def validate_collect(cfg: DictConfig, system: Any) -> None:
    """collect settings, before the robot or the controller is built."""
    validate(cfg, COLLECT, system_dims(system))
    _pair(cfg, "controller.u_low", "controller.u_high")
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


def validate_export(cfg: DictConfig, system: Any) -> None:
    """export settings, before the network is loaded."""
    validate(cfg, EXPORT, system_dims(system))


def job_system(cfg: DictConfig, validate: Callable[[DictConfig, Any], None]) -> Any:
    """The job's System from cfg.system, its settings checked against it and the CPU threads set: how jobs start."""
    from pinnmpc.systems.registry import build_system  # torch and the arms load only when a job runs
    from pinnmpc.util.threads import use_threads

    system = build_system(cfg.system)
    validate_system(cfg, system)
    validate(cfg, system)
    use_threads(cfg.threads)
    return system
