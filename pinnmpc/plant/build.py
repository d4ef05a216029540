"""The simulated robot of a closed loop or benchmark, built from the plant settings (conf/plant/)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from pinnmpc.plant.base import Plant
from pinnmpc.plant.scipy_plant import ScipyPlant
from pinnmpc.plant.settings import FrankaPlantSettings, MujocoPlantSettings, plant_settings
from pinnmpc.systems.base import System


def plant_system(system: System, cfg: Any) -> System:
    """The simulated robot: the model with optional friction/mass mismatch (never seen by the controller)."""
    if cfg.friction_scale == 1.0 and cfg.mass_scale == 1.0:
        return system
    return system.with_mismatch(friction_scale=cfg.friction_scale, mass_scale=cfg.mass_scale)


def simulated_arm(system: System, system_cfg: Any) -> System:
    """The arm the plant simulates: for a model identified from a robot's logs (`identified_from` in its config) the
    nominal arm it was fitted to, whose `robots` are the real ones; else the system itself."""
    origin = (system_cfg or {}).get("identified_from") if hasattr(system_cfg, "get") else None
    if not origin:
        return system
    from pinnmpc.systems.registry import load_system

    return load_system(str(origin["system"]))


def make_plant(
    system: System, cfg: Any, tau: float, robots: Mapping[str, Any] | None = None, run_dir: Path | None = None
) -> Plant:
    """The simulated robot of every closed loop (and of the bench's plant rows) from the plant settings (a config
    node or dict, checked: pinnmpc/plant/settings.py): scipy's solve_ivp on the model, or MuJoCo on the arm's
    URDF as one of the system's `robots` (read here alone)."""
    if isinstance(cfg, DictConfig):
        cfg = OmegaConf.to_container(cfg, resolve=True)
    settings = plant_settings(cfg)
    if isinstance(settings, FrankaPlantSettings):
        from pinnmpc.plant.franka import FrankaPlant  # franky loads only for its plant

        return FrankaPlant(system, tau, settings, run_dir)
    if isinstance(settings, MujocoPlantSettings):
        from pinnmpc.plant.mujoco_robot import make_mujoco_plant  # MuJoCo loads only for its plant

        if isinstance(robots, DictConfig):
            robots = OmegaConf.to_container(robots, resolve=True)
        return make_mujoco_plant(
            system,
            tau,
            robots,
            settings.robot,
            friction_scale=settings.friction_scale,
            mass_scale=settings.mass_scale,
            substeps=settings.substeps,
        )
    scaled = plant_system(system, settings)
    return ScipyPlant(
        scaled,
        tau,
        settings.method,
        settings.rtol,
        settings.atol,
        settings.chatter_flips,
        settings.stick_slip_tighten,
        settings.max_switches,
    )
