"""The bench's settings: the sizes of its sections, and at least one section to run."""

from __future__ import annotations

from typing import Any

from omegaconf import DictConfig, OmegaConf

from pinnmpc.simulation.settings import validate_plant
from pinnmpc.systems.settings import system_dims
from pinnmpc.util import checks as c
from pinnmpc.util.checks import SEED, Check, SettingError

BENCH: dict[str, Check] = {  # the sizes of its sections (a zero or empty one failed deep inside a section)
    "threads": c.integer(1),
    "seed": SEED,
    "failure.max_fallback_fraction": c.real(0.0, 1.0),
    "step.batch_sizes": c.listof(c.integer(1)),
    "step.n_states": c.integer(1),
    "step.repeats": c.integer(1),
    "step.warmup": c.integer(0),
    "step.rk45_loop_repeats": c.integer(1),
    "closed_loop.max_steps": c.optional(c.integer(1)),
    "robot.references": c.listof(c.text()),
    "robot.adapted": c.optional(c.text()),
    "robot.identified": c.optional(c.text()),
    "robot.logs": c.optional(c.listof(c.text())),
    "robot.rk4_steps": c.integer(1),
    "robot.classical_variants": c.boolean(),
    "floor.horizons": c.listof(c.integer(1)),
    "floor.max_steps": c.optional(c.integer(1)),
    "floor.cold.horizon": c.integer(1),
    "floor.cold.enabled": c.boolean(),
    "floor.cold.jump": c.real(),
    "floor.cold.ahead": c.real(0.0, 1.0, lo_open=True),
    "floor.cold.max_steps": c.integer(2),
    "floor.cold.repeats": c.integer(1),
    "targets.floor_ratio": c.optional(c.by_horizon()),
    "targets.cold_iterations": c.optional(c.integer(1)),
    "targets.cold_ratio": c.optional(c.positive()),
    "targets.peer_speedup": c.optional(c.positive()),
    "targets.classical_speedup": c.optional(c.positive()),
    "peers.horizons": c.listof(c.integer(1)),
    "peers.max_steps": c.optional(c.integer(1)),
    "peers.qpsols": c.listof(c.one_of("qrqp", "hpipm", "osqp"), empty=True),
    "peers.shared": c.listof(c.text(), empty=True),
    "optimality.n_states": c.integer(1),
    "optimality.random_starts": c.integer(0),
    "scaling.horizons": c.listof(c.integer(1)),
    "scaling.batch_sizes": c.listof(c.integer(1)),
    "scaling.base_batch": c.integer(1),
    "scaling.base_horizon": c.optional(c.integer(1)),
    "scaling.repeats": c.integer(1),
    "scaling.warmup": c.integer(0),
    "scaling.step_batch_sizes": c.listof(c.integer(1)),
    "scaling.step_repeats": c.integer(1),
    "scaling.step_warmup": c.integer(0),
}


BENCH_SECTIONS = ("step", "closed_loop", "optimality", "scaling", "classical", "robot", "kinds", "floor", "peers")


def validate_bench(cfg: DictConfig, system: Any) -> None:
    """bench settings: the sections' sizes, and at least one section to run."""
    c.validate(cfg, BENCH, system_dims(system))
    validate_plant(cfg)
    if not any(OmegaConf.select(cfg, f"{name}.enabled", default=False) for name in BENCH_SECTIONS):
        keys = ", ".join(f"{name}.enabled" for name in BENCH_SECTIONS)
        raise SettingError(f"every bench section is off ({keys} all false); expected at least one enabled")
