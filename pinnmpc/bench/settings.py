"""The bench's settings: the sizes of its sections, and at least one section to run."""

from __future__ import annotations

from typing import Any

from omegaconf import DictConfig, OmegaConf

from pinnmpc.simulation.settings import validate_plant
from pinnmpc.systems.settings import system_dims
from pinnmpc.util.checks import (
    SEED,
    Check,
    SettingError,
    integer,
    listof,
    optional,
    real,
    text,
    validate,
)

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


def validate_bench(cfg: DictConfig, system: Any) -> None:
    """bench settings: the sections' sizes, and at least one section to run."""
    validate(cfg, BENCH, system_dims(system))
    validate_plant(cfg)
    if not any(OmegaConf.select(cfg, f"{name}.enabled", default=False) for name in BENCH_SECTIONS):
        keys = ", ".join(f"{name}.enabled" for name in BENCH_SECTIONS)
        raise SettingError(f"every bench section is off ({keys} all false); expected at least one enabled")
