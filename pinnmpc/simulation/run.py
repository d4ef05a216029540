"""A closed loop from its config, as `python -m pinnmpc.closed_loop` runs it: checks, the loop, metrics, files."""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig

from pinnmpc.controller.nmpc import Controller
from pinnmpc.plant.build import make_plant
from pinnmpc.references.data import Reference
from pinnmpc.references.files import out_of_box
from pinnmpc.simulation.loop import LoopResult, divergence_box, run_loop
from pinnmpc.simulation.metrics import limits_and_saturation, metrics, verdict
from pinnmpc.simulation.setup import (
    arm_differences,
    bounds_outside,
    build_controller,
    checked_start,
    controller_box,
    system_reference,
    warn_jumps,
    warn_limit_margin,
)
from pinnmpc.systems.base import System
from pinnmpc.util.io import save_json, save_npz
from pinnmpc.util.settings import job_system, validate_closed_loop
from pinnmpc.util.signals import StopSignal

log = logging.getLogger(__name__)


def run_closed_loop(cfg: DictConfig, run_dir: Path, stop: StopSignal | None = None) -> dict[str, Any]:
    """Check the settings, load controller and reference, run the loop (until the end, a plant failure or a signal
    to stop), write metrics.json, trajectory.npz and plots."""
    system: System = job_system(cfg, validate_closed_loop)
    start = checked_start(cfg, system)
    controller, domain, tau = build_controller(cfg, system)
    differs = arm_differences(getattr(getattr(controller, "surrogate", None), "meta", None), cfg)
    if differs:  # before the run: a network of another arm tracks whatever it tracks
        log.warning(
            "WARNING: the network was trained for another description of this arm (system.dynamics %s differ): "
            "it predicts a different arm from the one the plant simulates",
            ", ".join(differs),
        )
    if cfg.tau is not None and abs(cfg.tau - tau) > 1e-12:
        raise ValueError(
            f"tau={cfg.tau} differs from the controller model's tau={tau} (a PINN predicts one period of its tau)"
        )
    ref = system_reference(cfg, system, tau)
    warn_jumps(ref, system)
    warn_limit_margin(ref, system, cfg.controller.get("joint_limits"))
    box = domain if domain is not None else system.state_box
    dist = out_of_box(ref, box.low, box.high)
    if dist > 0:
        what = "the surrogate's training box" if domain is not None else "the system's state box"
        log.warning("reference leaves %s by up to %.3g; tracking there is extrapolation", what, dist)
    plant = make_plant(system, cfg.plant, tau, cfg.system.get("robots"))
    run = run_loop(
        controller,
        plant,
        ref,
        x0=start,
        max_steps=cfg.max_steps,
        domain=domain,
        state_box=divergence_box(system),
        noise_sigma=cfg.noise_sigma,
        seed=cfg.seed,
        progress=cfg.progress,
        stop=None if stop is None else (lambda: stop.requested),
    )
    result = metrics(ref, run, controller, plant, system.state_names, system.state_units)
    failure = cfg.get("failure") or {}
    result.update(limits_and_saturation(run, controller, system))
    result["status"] = verdict(result, float(failure.get("max_fallback_fraction", 1.0)))
    result["input_bounds_outside_box"] = bool(domain is not None and bounds_outside(cfg, controller_box(controller)))
    result["plant_mismatch"] = {
        "friction_scale": float(cfg.plant.friction_scale),
        "mass_scale": float(cfg.plant.mass_scale),
    }
    result["plant"] = {"kind": str(cfg.plant.get("kind", "scipy")), "robot": cfg.plant.get("robot")}
    # the headline says "did not follow" past this final error (the robustness grid's bound of a bounded run)
    result["tracking_bound"] = float(cfg.system.get("robustness", {}).get("bound", math.inf))
    # how far a user's start x0 lies off the reference's first state (0: it starts on it)
    result["start_off_reference"] = 0.0 if start is None else float(np.abs(np.asarray(start) - ref.x[0]).max())
    result["network_arm_differs"] = differs  # system.dynamics keys
    st = controller.stats
    n = len(run.x)
    save_npz(
        run_dir / "trajectory.npz",
        t=ref.t[:n],
        x=run.x,
        x_ref=ref.x[:n],
        u=run.u,
        ocp_time_s=np.array([s.time_s for s in st]),
        iterations=np.array([s.iterations for s in st]),
        cost=np.array([s.cost for s in st]),
        converged=np.array([s.converged for s in st]),
        fallback=np.array([s.fallback for s in st]),
    )
    save_json(run_dir / "metrics.json", result)
    if cfg.plots and len(run.u):
        write_plots(cfg, system, ref, run, controller, run_dir)
    return result


def write_plots(
    cfg: DictConfig, system: System, ref: Reference, run: LoopResult, controller: Controller, run_dir: Path
) -> None:
    """closed_loop.png, and with animate=true closed_loop.gif of the arm (stick drawing from its kinematics)."""
    from pinnmpc.util import plots

    n = len(run.x)
    title = f"{system.name}: closed loop on {ref.name} ({controller.describe()['solver']})"
    labels = plots.Labels.of(system)
    low, high = np.asarray(controller.low).tolist(), np.asarray(controller.high).tolist()
    fig = plots.tracking_figure(ref.t[:n], ref.x[:n], run.x, run.u, low, high, labels, title=title)
    plots.save_figure(fig, run_dir / "closed_loop.png")
    if cfg.animate:
        nq = system.nq
        error = np.abs(run.x[:, :nq] - ref.x[:n, :nq]).max(axis=1)
        points_ref, points = system.kinematics(ref.x[:n, :nq]), system.kinematics(run.x[:, :nq])
        gif_title = f"{system.name} on {ref.name}"
        plots.animate_arm(
            ref.t[:n],
            points_ref,
            points,
            run_dir / "closed_loop.gif",
            title=gif_title,
            error=error,
            progress=cfg.progress,
        )
