"""The simulated robot of a closed loop or benchmark, built from the plant settings (conf/plant/)."""

from __future__ import annotations

from omegaconf import DictConfig

from pinnmpc.plant.scipy_plant import ScipyPlant
from pinnmpc.systems.base import System


def plant_system(system: System, cfg: DictConfig) -> System:
    """The simulated robot: the model with optional friction/mass mismatch (never seen by the controller)."""
    if cfg.friction_scale == 1.0 and cfg.mass_scale == 1.0:
        return system
    return system.with_mismatch(friction_scale=cfg.friction_scale, mass_scale=cfg.mass_scale)


def make_plant(system: System, cfg: DictConfig, tau: float) -> ScipyPlant:
    """The simulated robot of every closed loop (and of the bench's RK45 row) from the plant settings."""
    return ScipyPlant(
        plant_system(system, cfg),
        tau,
        cfg.method,
        cfg.rtol,
        cfg.atol,
        cfg.chatter_flips,
        cfg.stick_slip_tighten,
        int(cfg.max_switches),
    )
