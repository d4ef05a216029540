"""The training settings (`module`, `data`): structured configs whose fields, types and defaults are the settings of
PINNModule and CollocationDataModule and whose field docstrings document them; both classes take their keyword
defaults from here. Each field is checked on its own here; what needs the system (a list of nx entries) or another
setting (t_high against tau and t_max) is checked where that is known (pinnmpc/training/job_settings.py, the
classes)."""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

from pinnmpc.util.checks import (
    Check,
    Dims,
    boolean,
    check_settings,
    integer,
    listof,
    one_of,
    optional,
    positive,
    real,
    text,
)

RESIDUAL_FORMS = ("explicit", "mass")  # dx/dt - f(x, u) | the paper's M-multiplied form (PowerCube only)
DTYPES = ("float32", "float64")  # training precisions (PINNModule maps them to torch dtypes)
OPTIMIZERS = ("lbfgs", "ssbfgs")  # limited-memory BFGS (the paper's) | dense self-scaled BFGS (ssbfgs.py)
SSBFGS_VARIANTS = ("ssbfgs", "ssbroyden", "bfgs")  # ssbfgs.VARIANTS, named here without importing torch
HESSIAN_DTYPES = ("float32", "float64")  # ssbfgs.HESSIAN_DTYPES' names


def _scale(v: Any, d: Dims) -> str | None:
    """'auto' or one positive number per state (the count is PINNModule's to check: it knows nx)."""
    ok = v == "auto" or listof(positive())(v, d) is None
    return None if ok else "auto or a non-empty list, each entry a finite number > 0"


def _weights(v: Any, d: Dims) -> str | None:
    """null or one positive multiplier per state (the count is checked where nx is known)."""
    ok = v is None or listof(positive())(v, d) is None
    return None if ok else "null or a non-empty list, each entry a finite number > 0"


def _pool(v: Any, d: Dims) -> str | None:
    """0 (plain LHS) or a pool of at least two candidates per point (one would be no choice)."""
    return None if integer(0, 0)(v, d) is None or integer(2)(v, d) is None else "0 (off) or an integer >= 2"


def _fraction(v: Any, d: Dims) -> str | None:
    """A fraction strictly inside (0, 1): some episodes train, some validate."""
    return None if real(0.0, 1.0, lo_open=True)(v, d) is None and v < 1 else "a finite number in (0, 1)"


@dataclass
class ModuleSettings:
    """`module=pinn` (conf/module/pinn.yaml): losses and optimiser of pinnmpc.training.module.PINNModule."""

    _target_: str = "pinnmpc.training.module.PINNModule"
    """The class `python -m pinnmpc.train` instantiates with these settings."""
    residual_form: str = "explicit"
    """explicit: dx/dt - f(x, u); mass: the paper's M-multiplied form."""
    residual_scale: Any = "auto"
    """Per-component residual divisor (nx numbers); auto: output_scale / t_max (explicit form), times the base's
    residual level with stage.base."""
    kinematic_weight: float = 3.0
    """Extra weight on the kinematic residual rows dq/dt - v (x = (q, v) systems; 1: off)."""
    robust_delta: float | None = None
    """Huber threshold on each scaled residual: squares below, linear above (null: squares; the largest residuals
    sit at the stiff start of a step and joint B's friction switch; with stage.base the residual unit is the base's
    residual level, so ~1 there)."""
    weight_physics: float = 1.0
    """Weight of the physics loss."""
    weight_data: float = 1.0
    """Weight of the data loss at t = 0 (no effect with ic=hard)."""
    weight_anchor: float = 1000.0
    """Weight of the anchor loss (data.n_anchor > 0): squared error of x(t) - x0 in output units; at 1 it is ~1% of
    the physics loss, 100 and 1000 measured (docs/training-findings.md); 0: no anchors drawn at all (as
    data.n_anchor=0)."""
    weight_robot: float = 1000.0
    """Weight of the robot-data loss (data.logs): squared error of x(t) - x0 on logged transitions in output units,
    as the anchor loss; the physics loss (weight_physics) keeps the nominal model where the logs do not reach."""
    robot_delta: float | None = None
    """Huber's delta for the robot-data loss, in output units (null: squares): beyond it an error counts linearly,
    so the few transitions no (t, x0, u) model can explain (a robot's command ramp, its memory) do not set the fit
    where the closed loop runs (docs/franka.md)."""
    anchor_state_weight: list[float] | None = None
    """Per-state multiplier of the anchor and robot-data losses (nx numbers; null: all 1): more on a state whose
    target is the tightest in output units (docs/training.md)."""
    dtype: str = "float32"
    """Training precision: float32 (the faster on CPU) | float64."""
    adam_epochs: int = 0
    """Adam warm-up epochs before L-BFGS (0: L-BFGS from the start)."""
    adam_lr: float = 1.0e-3
    """Adam learning rate during warm-up."""
    optimizer: str = "ssbfgs"
    """ssbfgs: dense self-scaled BFGS (Urban et al. 2024; docs/training.md), its n x n inverse Hessian kept across
    point redraws (networks up to ~40k parameters) | lbfgs: the paper's."""
    ssbfgs_variant: str = "ssbfgs"
    """With optimizer=ssbfgs: ssbfgs (self-scaled BFGS, Urban et al. 2024) | ssbroyden (self-scaled Broyden, the
    family parameter chosen per step too) | bfgs (plain)."""
    hessian_dtype: str = "float32"
    """With optimizer=ssbfgs: precision of the inverse Hessian: float32 (half the memory and passes, the faster per
    minute: docs/training-findings.md) | float64."""
    hessian_buffer: int = 16
    """With optimizer=ssbfgs: updates kept aside and folded into the n x n matrix together (1: every update at once;
    the iterates agree to rounding, larger passes over it less)."""
    lbfgs_lr: float = 1.0
    """L-BFGS step length (strong Wolfe line search)."""
    lbfgs_max_iter: int = 50
    """Quasi-Newton iterations per epoch (one epoch = one optimiser call)."""
    lbfgs_history: int = 50
    """L-BFGS history size."""
    lbfgs_tolerance_grad: float = 1.0e-9
    """L-BFGS stops an epoch early below this gradient norm ..."""
    lbfgs_tolerance_change: float = 1.0e-12
    """... or below this change in loss/parameters."""
    stall_min_evals: int = 3
    """Fewer function evaluations in an epoch (or no decrease at all) = stalled: reset the L-BFGS history, redraw
    points."""
    stall_rel_tol: float = 0.0
    """... as is an epoch that lowers the loss by less than this fraction (0: off; 1e-6 with stall_redraw=true
    redraws so often that accuracy suffers, docs/powercube.md)."""
    stall_redraw: bool = True
    """On a stall also redraw the collocation points (false: only reset the history)."""

    def __post_init__(self) -> None:
        check_settings("module", self, MODULE_CHECKS)


MODULE_CHECKS: dict[str, Check] = {
    "_target_": text(),
    "residual_form": one_of(*RESIDUAL_FORMS),
    "residual_scale": _scale,
    "kinematic_weight": positive(),
    "robust_delta": optional(positive()),
    "weight_physics": real(0.0),
    "weight_data": real(0.0),
    "weight_anchor": real(0.0),
    "weight_robot": real(0.0),
    "robot_delta": optional(positive()),
    "anchor_state_weight": _weights,  # nx entries: checked where nx is known
    "dtype": one_of(*DTYPES),
    "adam_epochs": integer(0),
    "adam_lr": positive(),
    "optimizer": one_of(*OPTIMIZERS),
    "ssbfgs_variant": one_of(*SSBFGS_VARIANTS),
    "hessian_dtype": one_of(*HESSIAN_DTYPES),
    "hessian_buffer": integer(1),
    "lbfgs_lr": positive(),
    "lbfgs_max_iter": integer(1),
    "lbfgs_history": integer(1),
    "lbfgs_tolerance_grad": real(0.0),
    "lbfgs_tolerance_change": real(0.0),
    "stall_min_evals": integer(0),
    "stall_rel_tol": real(0.0),
    "stall_redraw": boolean(),
}


@dataclass
class DataSettings:
    """`data=collocation` (conf/data/collocation.yaml): Latin-hypercube collocation/data points and the held-out
    validation set of pinnmpc.training.data.CollocationDataModule."""

    _target_: str = "pinnmpc.training.data.CollocationDataModule"
    """The class `python -m pinnmpc.train` instantiates with these settings."""
    n_collocation: int = 20000
    """Physics-loss points in the 7-D box (paper: 20000)."""
    n_data: int = 100
    """Data points at t = 0 (paper: 100); only used by the data loss."""
    resample_every: int = 10
    """Redraw all points every this many epochs (0: never); 10 x 50 iterations: a dense BFGS fits one draw closely,
    fresh points keep it fitting the flow, not the draw."""
    resample_epochs: list[int] = field(default_factory=list)
    """Extra epochs at which to redraw (paper: halfway)."""
    n_val: int = 1000
    """Held-out random (x0, u) for the one-step validation RMSE at t = tau."""
    val_h: float = 1.0e-4
    """RK4 step of the accurate validation reference, s."""
    adaptive_pool: int = 0
    """Residual-adaptive redraws (RAR-D): candidates per point drawn by LHS, the kept ones sampled with density
    ~ r^k / mean(r^k) + c by the current residual r (0: plain LHS)."""
    adaptive_k: float = 1.0
    """RAR-D exponent k: larger concentrates points harder on the worst residuals."""
    adaptive_c: float = 1.0
    """RAR-D floor c: larger keeps the draw closer to uniform over the box."""
    t_high: float | None = None
    """Collocation times drawn from [0, t_high], tau <= t_high <= t_max (null: t_max, the paper's; tau: only the
    part of the flow the controller uses, x(tau) does not depend on later residuals)."""
    n_anchor: int = 4000
    """Anchor points (t, x0, u) whose accurate x(t) comes from fine RK4 of the same ODE, fitted by the anchor loss
    (module.weight_anchor) next to the residual; 0: off, a pure PINN (docs/training-findings.md: PowerCube angle
    errors 2-3x lower at the same minutes)."""
    anchor_h: float = 1.0e-4
    """RK4 step of the anchors' reference solution, s (redrawn with the collocation points)."""
    logs: list[str] = field(default_factory=list)
    """Robot logs (.npz or .csv from `python -m pinnmpc.collect`) to fine-tune on: every pair of samples within one
    hold period is a target x(t) of the robot-data loss (module.weight_robot); whole episodes held out
    (val_episodes) make the validation set."""
    n_robot: int = 0
    """Logged transitions per draw of the robot-data loss (0: all of them; a random subset, redrawn with the
    collocation points, bounds the cost of very long logs)."""
    val_episodes: float = 0.2
    """Fraction of each log's episodes held out for validation: with logs, the validation RMSE (and the best
    checkpoint) is the one-step error at tau on the robot, not on the model."""
    robot_max_input_step: float | None = None
    """Leave out of the robot-data loss and the validation the periods whose input moved further than this from the
    previous period's (any input, input units; null: keep all): where a robot ramps its command (franky), those
    periods depend on more than (t, x0, u), and fitting them spoils the fit where the closed loop runs
    (docs/franka.md)."""

    def __post_init__(self) -> None:
        check_settings("data", self, DATA_CHECKS)


DATA_CHECKS: dict[str, Check] = {
    "_target_": text(),
    "n_collocation": integer(1),
    "n_data": integer(0),
    "resample_every": integer(0),
    "resample_epochs": listof(integer(0), empty=True),
    "n_val": integer(1),
    "val_h": positive(),
    "adaptive_pool": _pool,
    "adaptive_k": real(0.0),
    "adaptive_c": real(0.0),
    "t_high": optional(positive()),  # tau <= t_high <= t_max: checked by CollocationDataModule
    "n_anchor": integer(0),
    "anchor_h": positive(),
    "logs": listof(text(), empty=True),
    "n_robot": integer(0),
    "val_episodes": _fraction,
    "robot_max_input_step": optional(positive()),
}

SECTIONS: dict[str, dict[str, type]] = {"module": {"pinn": ModuleSettings}, "data": {"collocation": DataSettings}}


def section_settings(section: str, cfg: Any) -> ModuleSettings | DataSettings:
    """The checked settings of a module or data config node (or dict): a bad or unknown key is one line naming it."""
    values = dict(cfg.items()) if hasattr(cfg, "items") else dict(cfg)
    (name, cls), *_ = SECTIONS[section].items()
    known = [f.name for f in fields(cls)]
    unknown = sorted(set(values) - set(known))
    if unknown:
        raise ValueError(f"{section}.{unknown[0]}: not a setting of {section}={name}; expected one of {known}")
    return cls(**values)


def register_configs() -> None:
    """The module's and the data module's settings as the structured configs behind conf/module/pinn.yaml and
    conf/data/collocation.yaml (groups schema/module, schema/data)."""
    from hydra.core.config_store import ConfigStore

    store = ConfigStore.instance()
    for section, options in SECTIONS.items():
        for name, cls in options.items():
            store.store(group=f"schema/{section}", name=name, node=cls)
