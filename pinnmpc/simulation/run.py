"""A closed loop from its config, as `python -m pinnmpc.closed_loop` runs it: checks, the loop, metrics, files."""

from __future__ import annotations

import contextlib
import logging
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig

from pinnmpc.controller.base import Controller
from pinnmpc.plant.build import make_plant, simulated_arm
from pinnmpc.references.data import Reference
from pinnmpc.references.files import out_of_box
from pinnmpc.simulation.fault_setup import plan_faults
from pinnmpc.simulation.loop import LoopResult, divergence_box, model_step, run_loop
from pinnmpc.simulation.metrics import faults_metrics, limits_and_saturation, metrics, robot_outcome, verdict
from pinnmpc.simulation.model_fit import model_fit
from pinnmpc.simulation.settings import validate_closed_loop, within_plant_limits
from pinnmpc.simulation.setup import (
    arm_differences,
    bounds_outside,
    build_controller,
    checked_start,
    controller_box,
    system_reference,
    warn_jumps,
    warn_limit_margin,
    warn_long_horizon,
)
from pinnmpc.systems.base import System
from pinnmpc.systems.settings import job_system
from pinnmpc.util.io import save_json, save_npz
from pinnmpc.util.signals import StopSignal

log = logging.getLogger(__name__)


class OutputError(OSError):
    """An output file could not be written (disk full, read-only dir, a folder in the way): one line naming it."""


def run_closed_loop(
    cfg: DictConfig,
    run_dir: Path,
    stop: StopSignal | None = None,
    announce: Callable[[dict[str, Any]], None] | None = None,
) -> dict[str, Any]:
    """Check the settings, load controller and reference, run the loop (until the end, a plant failure or a signal
    to stop), write trajectory.npz and plots, announce the result (the caller's log line), and metrics.json last:
    its status is "ok" only when everything before it was written; a write that fails raises OutputError."""
    system: System = job_system(cfg, validate_closed_loop)
    within_plant_limits(cfg, system)
    start = checked_start(cfg, system)
    warn_long_horizon(cfg)
    controller, domain, tau = build_controller(cfg, system)
    differs = arm_differences(getattr(getattr(controller, "surrogate", None), "meta", None), cfg)
    if differs:  # before the run: a network of another arm tracks whatever it tracks
        log.warning(
            "the network was trained for another description of this arm (system.dynamics %s differ): "
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
    arm = simulated_arm(system, cfg.system)  # the robot's arm: for an identified model, the nominal one
    plant = make_plant(arm, cfg.plant, tau, cfg.system.get("robots"), run_dir)
    try:  # a robot plant stops its arm and its server however the run ends (the end, an error, a signal)
        return _run_on_plant(cfg, run_dir, stop, announce, system, controller, domain, tau, ref, start, arm, plant,
                             differs)  # fmt: skip
    finally:
        if hasattr(plant, "close"):
            plant.close()


def _run_on_plant(
    cfg: DictConfig,
    run_dir: Path,
    stop: StopSignal | None,
    announce: Callable[[dict[str, Any]], None] | None,
    system: System,
    controller: Controller,
    domain: Any,
    tau: float,
    ref: Reference,
    start: Any,
    arm: System,
    plant: Any,
    differs: list[str],
) -> dict[str, Any]:
    """The loop on a built plant, its metrics and files (run_closed_loop closes the plant afterwards)."""
    if hasattr(plant, "start"):  # a robot: moved to the reference's start, the loop begins where it measures
        start = plant.start(np.asarray(ref.x[0] if start is None else start))
    monitor = getattr(controller, "prediction_error", None)
    plan = plan_faults(
        cfg.get("faults"),
        arm,
        plant,
        plant_cfg=cfg.plant,
        robots=cfg.system.get("robots"),
        noise_sigma=float(cfg.noise_sigma),
        seed=int(cfg.seed),
        predict=None if monitor is None else model_step(monitor, len(system.state_names)),
    )
    run = run_loop(
        controller,
        plan.plant,
        ref,
        x0=start,
        max_steps=cfg.max_steps,
        domain=domain,
        state_box=divergence_box(system),
        noise_sigma=cfg.noise_sigma,
        seed=cfg.seed,
        progress=cfg.progress,
        stop=None if stop is None else (lambda: stop.requested),
        sensor=plan.sensor,
        guard=plan.guard,
    )
    result = metrics(ref, run, controller, plan.plant, system.state_names, system.state_units)
    result.update(model_fit(result["model_monitor"], controller, system, float(cfg.noise_sigma)))
    result["faults"] = faults_metrics(run, ref, system.nq, tau, plan.recovery)
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
    result["followed"] = bool(result["final_position_error_max"] <= result["tracking_bound"])
    # how far a user's start x0 lies off the reference's first state (0: it starts on it)
    result["start_off_reference"] = 0.0 if start is None else float(np.abs(np.asarray(start) - ref.x[0]).max())
    result["network_arm_differs"] = differs  # system.dynamics keys
    robot, result["status"] = robot_outcome(plant, result["status"])  # a robot: errors, safety, at rest
    result.update(robot)
    write_outputs(cfg, system, ref, run, controller, run_dir, result, announce)
    return result


def write_outputs(
    cfg: DictConfig,
    system: System,
    ref: Reference,
    run: LoopResult,
    controller: Controller,
    run_dir: Path,
    result: dict[str, Any],
    announce: Callable[[dict[str, Any]], None] | None,
) -> None:
    """trajectory.npz, the plots, the announcement, then metrics.json: a failed write leaves metrics.json with a
    status naming it (or none where metrics.json itself cannot be written) and raises OutputError."""
    st = controller.stats
    n = len(run.x)
    path = run_dir / "trajectory.npz"
    try:
        save_npz(
            path,
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
        path = run_dir / "closed_loop.png"
        if cfg.plots and len(run.u):
            write_plots(cfg, system, ref, run, controller, run_dir)
        path = run_dir  # the log line (the caller's announcement)
        if announce is not None:
            announce(result)
    except OSError as e:
        message = f"cannot write {path}: {e.strerror or e}"
        result["status"] = f"failed: {message}"
        with contextlib.suppress(OSError):  # no metrics.json then: nothing claims "ok"
            save_json(run_dir / "metrics.json", result)
        raise OutputError(message) from None
    try:
        save_json(run_dir / "metrics.json", result)
    except OSError as e:
        raise OutputError(f"cannot write {run_dir / 'metrics.json'}: {e.strerror or e}") from None


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
