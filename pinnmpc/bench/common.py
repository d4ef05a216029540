"""What every section shares, built one way: the plant, the references, controller configs, random states."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf, open_dict

from pinnmpc.plant.base import Plant
from pinnmpc.plant.build import make_plant as closed_loop_plant
from pinnmpc.plant.build import simulated_arm
from pinnmpc.plant.settings import ScipyPlantSettings
from pinnmpc.references.files import PROJECT_ROOT, Reference, resolve_reference_path
from pinnmpc.simulation.setup import system_reference
from pinnmpc.systems.base import System
from pinnmpc.systems.sampling import random_pairs

STATUS_CHARS = 40  # a failed loop's status is cut to this many characters in its table cell
NO_DISTURBANCE = {"gain": 0.0}  # controller.disturbance override: the paper's controller, no offset-free MPC


def make_plant(cfg: DictConfig, system: System, tau: float) -> Plant:
    """The simulated robot of every closed loop and of the RK45 row, as pinnmpc.closed_loop builds it."""
    return closed_loop_plant(simulated_arm(system, cfg.system), cfg.plant, tau, cfg.system.get("robots"))


def on_the_model(cfg: DictConfig) -> DictConfig:
    """A copy of cfg with the nominal model as the plant (scipy, default settings): the plant of the rows that
    measure the model or the controller rather than the robot."""
    nominal = cfg.copy()
    with open_dict(nominal):
        nominal.plant = OmegaConf.structured(ScipyPlantSettings)
    return nominal


def plant_kind(cfg: DictConfig) -> str:
    """The plant's kind (scipy, mujoco, franka), as the sections name the plant they ran on."""
    return str(cfg.plant.get("kind", "scipy"))


def timing_cfg(cfg: DictConfig) -> DictConfig:
    """cfg for the sections that time the controller (the robot's paired OCP, floor, peers): on a real-time robot
    (plant=franka) the nominal model instead, as two controllers cannot take turns on one robot's clock, a peer
    slower than the period would trip the watchdog and the cold start's jump is no motion for an arm; cfg itself on
    a simulated plant."""
    return on_the_model(cfg) if plant_kind(cfg) == "franka" else cfg


def bench_reference(cfg: DictConfig, system: System, tau: float, name: str | None = None) -> Reference:
    """reference.path (auto: system.paper_reference where it exists, else the system's built-in),
    or the built-in `name`, on the grid of tau, as pinnmpc.closed_loop loads it."""
    path = None if name is not None else cfg.reference.path
    node = OmegaConf.create(
        {
            "reference": {"path": path, "name": cfg.reference.name if name is None else name},
            "system": {
                "references": OmegaConf.to_container(cfg.system.references, resolve=True),
                "paper_reference": cfg.system.get("paper_reference"),
            },
        }
    )
    return system_reference(node, system, tau)


def paper_reference_used(cfg: DictConfig) -> bool:
    """Whether the closed loops track the reference the paper's published row was measured on
    (system.paper_reference): only then does that row belong beside ours."""
    paper = cfg.system.get("paper_reference")
    used = resolve_reference_path(cfg.reference.path, paper)
    if not isinstance(paper, str) or used is None:
        return False
    return Path(used).resolve() == (PROJECT_ROOT / paper).resolve()


def paper_rows(cfg: DictConfig, reference: str | None) -> dict[str, Any] | None:
    """bench.json's `paper` block: the system's published numbers, without the closed-loop row where this bench
    did not track the paper's reference (`closed_loop_left_out` says so instead: a row beside ours on another
    reference compares nothing)."""
    paper = cfg.get("paper")
    if paper is None:
        return None
    out = OmegaConf.to_container(paper, resolve=True)
    if reference is not None and out.get("closed_loop") and not paper_reference_used(cfg):
        del out["closed_loop"]
        out["closed_loop_left_out"] = (
            f"measured on the paper's reference ({cfg.system.get('paper_reference')}), absent here or not chosen; "
            f"these closed loops tracked {reference}"
        )
    return out


def controller_cfg(cfg: DictConfig, **changes: Any) -> DictConfig:
    """The controller section with a few settings swapped (solver, horizon), everything else as configured."""
    return OmegaConf.merge(cfg.controller, changes)


def optimality_solvers(cfg: DictConfig) -> list[str]:
    """The solvers whose OCPs the optimality section re-solves: as configured, or every PINN row of section 2."""
    chosen = cfg.optimality.solvers
    if chosen is None:
        chosen = cfg.closed_loop.solvers if cfg.closed_loop.enabled else [cfg.controller.solver]
    return [str(s) for s in chosen]


def integrator_h(tau: float, h: float | None) -> float:
    """A fixed-step baseline's step: as configured, else tau / 10 (the paper's choice)."""
    return float(h) if h is not None else float(tau) / 10.0


def random_states(system: System, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """x0 uniform in the state box and u uniform in the input box (the training box), seeded."""
    x0, u = random_pairs(system, n, seed)
    return x0.numpy(), u.numpy()


def status_suffix(status: str) -> str:
    """Label suffix of a loop that did not end ok: its status, cut short."""
    return "" if status == "ok" else f" ({status[:STATUS_CHARS]})"
