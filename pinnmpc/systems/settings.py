"""The settings every job checks against its arm (the system config's per-joint lists) and how a job starts: its
System built, its own settings checked, its threads set."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from omegaconf import DictConfig

from pinnmpc.util import checks as c
from pinnmpc.util.checks import Check

SYSTEM: dict[str, Check] = {  # the per-joint lists of conf/system/<name>.yaml that only some jobs read
    "system.network.periodic": c.listof(c.joint_index(), empty=True),
    "system.network.angle_sums": c.listof(c.listof(c.joint_index()), empty=True),
    "system.targets.one_step_rmse": c.per_state_targets(),
    "system.targets.closed_loop_mae": c.per_state_targets(),
    "system.targets.classical_speedup": c.optional(c.positive()),
    "system.self_loop.x0": c.vector("nx"),
    "system.self_loop.amplitude": c.vector("nu"),
    "system.control.Q": c.weight("nx"),  # the NMPC's weights: checked before a training the controller comes after
    "system.control.R": c.weight("nu"),
    "system.control.disturbance_max": c.optional(c.vector("nx", c.real(0.0))),
    "system.control.rti_trust": c.optional(c.positive()),
}


def validate_system(cfg: DictConfig, system: Any) -> None:
    """The system config's per-joint lists against the arm its URDF builds, for every job (a new arm's config)."""
    c.validate(cfg, SYSTEM, system_dims(system))


def system_dims(system: Any) -> dict[str, int]:
    """nx and nu of a System (or anything with state and input names)."""
    return {"nx": len(system.state_names), "nu": len(system.input_names)}


def job_system(cfg: DictConfig, validate: Callable[[DictConfig, Any], None]) -> Any:
    """The job's System from cfg.system, its settings checked against it and the CPU threads set: how jobs start."""
    from pinnmpc.systems.registry import build_system  # torch and the arms load only when a job runs
    from pinnmpc.util.threads import use_threads

    system = build_system(cfg.system)
    validate_system(cfg, system)
    validate(cfg, system)
    use_threads(cfg.threads)
    return system
