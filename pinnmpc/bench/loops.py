"""Section 2: closed-loop tracking on the plant, one row per solver of the PINN controller, the same controller
on the true model (RK4) and the configured controller on the system's other built-in references."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig
from torch import Tensor

from pinnmpc.bench.common import (
    NO_DISTURBANCE,
    bench_reference,
    controller_cfg,
    integrator_h,
    make_plant,
    optimality_solvers,
)
from pinnmpc.bench.timing import as_numpy
from pinnmpc.controller.array_backend import Array
from pinnmpc.controller.base import Controller
from pinnmpc.controller.build import build_nmpc
from pinnmpc.controller.solvers import NO_WARM, Problem, SolveInfo, Solver
from pinnmpc.plant.build import simulated_arm
from pinnmpc.references.files import Reference
from pinnmpc.simulation.fault_setup import plan_faults
from pinnmpc.simulation.loop import divergence_box, model_step, run_loop
from pinnmpc.simulation.metrics import faults_metrics, limits_and_saturation, metrics, robot_outcome, verdict
from pinnmpc.surrogate.checkpoint import Surrogate
from pinnmpc.surrogate.flowmap import CompiledRK4, FlowMap, RK4Model
from pinnmpc.systems.base import Box, System

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class OCPProblem:
    """One OCP the closed loop solved (single problem, no batch dimension) and the solver's answer."""

    x0: Tensor
    x_ref: Tensor
    u_prev: Tensor
    U: Tensor
    disturbance: Tensor  # the additive disturbance the controller predicted with (zeros: none)


@dataclass
class RecordingSolver:
    """Wraps a solver and keeps every problem it solved, so the optimality section re-solves exactly those."""

    inner: Solver
    raw: list[tuple[np.ndarray, ...]] = field(default_factory=list)  # numpy copies: recording stays off the clock

    @property
    def problems(self) -> list[OCPProblem]:
        """The recorded problems as torch tensors."""
        return [OCPProblem(*(torch.from_numpy(a) for a in parts)) for parts in self.raw]

    @property
    def array_api(self) -> str:
        """The wrapped solver's array library, so the controller hands it its own kind of arrays."""
        return self.inner.array_api

    @property
    def rti(self) -> bool:
        """Whether the wrapped solver is a real-time iteration (the row's label and metrics say so)."""
        return bool(getattr(self.inner, "rti", False))

    def solve(self, problem: Problem, U0: Array, warm: Any = NO_WARM) -> tuple[Array, SolveInfo, Any]:
        """Delegate (the warm state passes through untouched), then record each problem with its projected solution."""
        U, info, next_warm = self.inner.solve(problem, U0, warm)
        Uc = np.clip(np.asarray(U, dtype=np.float64), np.asarray(problem.low), np.asarray(problem.high))
        ocp, x0, x_ref, u_prev = problem.ocp, problem.x0, problem.x_ref, problem.u_prev
        d = np.zeros(ocp.nx) if ocp.disturbance is None else ocp.disturbance
        for i in range(x0.shape[0]):
            self.raw.append(tuple(as_numpy(a).copy() for a in (x0[i], x_ref[i], u_prev[i], Uc[i], d)))
        return U, info, next_warm


def loop_row(
    cfg: DictConfig, system: System, controller: Controller, domain: Box | None, tau: float, ref: Reference
) -> dict[str, Any]:
    """One closed loop of any controller on the plant, summarised as a table row (the same protocol for all)."""
    plant = make_plant(cfg, system, tau)
    try:  # a robot plant (plant=franka) stops its arm and server however the loop ends
        return _loop_row(cfg, system, controller, domain, tau, ref, plant)
    finally:
        if hasattr(plant, "close"):
            plant.close()


def _loop_row(
    cfg: DictConfig, system: System, controller: Controller, domain: Box | None, tau: float, ref: Reference, plant: Any
) -> dict[str, Any]:
    """loop_row on a built plant; a robot is first moved to the reference's start."""
    monitor = getattr(controller, "prediction_error", None)
    x0 = plant.start(np.asarray(ref.x[0])) if hasattr(plant, "start") else None
    plan = plan_faults(  # faults: as in pinnmpc.closed_loop (all off by default)
        cfg.get("faults"),
        simulated_arm(system, cfg.system),
        plant,
        plant_cfg=cfg.plant,
        robots=cfg.system.get("robots"),
        noise_sigma=0.0,
        seed=int(cfg.seed),
        predict=None if monitor is None else model_step(monitor, len(system.state_names)),
    )
    start = time.perf_counter()
    steps, box = cfg.closed_loop.max_steps, divergence_box(system)  # a diverged loop stops, as in pinnmpc.closed_loop
    run = run_loop(
        controller,
        plan.plant,
        ref,
        x0=x0,
        max_steps=steps,
        domain=domain,
        state_box=box,
        seed=int(cfg.seed),
        progress=bool(cfg.progress),
        sensor=plan.sensor,
        guard=plan.guard,
    )
    wall = time.perf_counter() - start
    m = metrics(ref, run, controller, plan.plant, system.state_names)
    m["status"] = verdict(m, float(cfg.failure.max_fallback_fraction))  # too many fallbacks: failed
    ocp = m["ocp_time_s"]
    limits = limits_and_saturation(run, controller, system)
    robot, m["status"] = robot_outcome(plant, m["status"])  # a robot: libfranka's errors, the safety layer's acts
    return {
        **robot,
        "joint_limit_samples": limits["joint_limit_samples"],  # measured: samples past a joint limit
        "joint_limit_excess_max": limits["joint_limit_excess_max"],
        "over_period": int(m["over_period"]),  # solves longer than the control period (wall time)
        "solver": str(m["solver"]),
        "disturbance_gain": float(m["disturbance_gain"]),
        "prediction": str(m.get("prediction") or "none"),  # what predicts, where the controller says
        "real_time": bool(m.get("real_time")),  # one step per sample (a real-time iteration), not converged
        "status": m["status"],
        "steps": int(m["steps"]),
        "mae": m["mae"],
        "ocp_time_s": {k: ocp[k] for k in ("mean", "median", "p95", "p99", "max")},
        "plant_step_median_s": m["plant_step_time_s"]["median"],
        "ratio_ocp_to_plant": ocp["median"] / m["plant_step_time_s"]["median"],
        "iterations_mean": float(m["iterations"]["mean"]),
        "converged_fraction": float(m["converged_fraction"]),
        "fallbacks": int(m["fallbacks"]),
        "out_of_box_steps": int(m["out_of_box_steps"]),
        "wall_s": float(wall),
        "measurement_guard": m["measurement_guard"],  # readings rejected, inputs held (all 0 without faults)
        "faults": faults_metrics(run, ref, system.nq, tau, plan.recovery),  # each fault, what was done, recovery
    }


def run_controller(
    cfg: DictConfig, system: System, flow: FlowMap, ref: Reference, solver: str, record: bool, **changes: Any
) -> tuple[dict[str, Any], list[OCPProblem]]:
    """The configured NMPC with `solver` on a flow map, one closed loop; the row and, when asked, its OCPs."""
    nmpc = build_nmpc(controller_cfg(cfg, solver=solver, **changes), flow, system)
    recorder = RecordingSolver(nmpc.solver) if record else None
    if recorder is not None:
        nmpc.solver = recorder
    row = loop_row(cfg, system, nmpc, getattr(flow, "domain", None), flow.tau, ref)
    row["solver"] = solver
    return row, (recorder.problems if recorder is not None else [])


def bench_closed_loop(
    cfg: DictConfig, system: System, surrogate: Surrogate, ref: Reference
) -> tuple[dict[str, Any], dict[str, list[OCPProblem]]]:
    """PINN-MPC per solver and the true-model baseline on the same reference and plant."""
    cl = cfg.closed_loop
    rows: dict[str, dict[str, Any]] = {}
    problems: dict[str, list[OCPProblem]] = {}
    examined = set(optimality_solvers(cfg)) if cfg.optimality.enabled else set()
    for solver in cl.solvers:
        row, recorded = run_controller(cfg, system, surrogate, ref, solver, record=solver in examined)
        rows[f"pinn_{solver}"] = {"label": _label(solver, row), "model": "pinn", **row}
        if recorded:
            problems[solver] = recorded
        log.info("closed loop: PINN %s done in %.1f s", solver, row["wall_s"])
    if cl.paper_controller and float(cfg.controller.disturbance.gain) > 0:  # the same without offset-free MPC
        solver = str(cfg.controller.solver)
        row, _ = run_controller(cfg, system, surrogate, ref, solver, record=False, disturbance=NO_DISTURBANCE)
        rows[f"pinn_{solver}_paper"] = {"label": _label(solver, row), "model": "pinn", **row}
        log.info("closed loop: PINN %s without disturbance estimate done in %.1f s", solver, row["wall_s"])
    if cl.true_model:
        model, what = true_model(cfg, system, surrogate.tau)
        for solver in cl.true_model_solvers:
            row, _ = run_controller(cfg, system, model, ref, solver, record=False)
            rows[f"true_rk4_{solver}"] = {"label": f"true model ({what}), {solver}", "model": "rk4", **row}
            log.info("closed loop: true model %s done in %.1f s", solver, row["wall_s"])
    names = more_references(cfg)
    others = {name: other_reference_row(cfg, system, surrogate, name) for name in names}
    result = {
        "reference": ref.name,
        "horizon": int(cfg.controller.horizon),
        "true_model_backend": str(cl.true_model_backend),
        "rows": rows,
        "references": others,
    }
    return result, problems


def true_model(cfg: DictConfig, system: System, tau: float) -> tuple[FlowMap, str]:
    """The true dynamics by RK4 as a flow map for the controller, and its label: torch (autodiff through the
    torch rhs) or compiled (CasADi C with its numpy fast path: the practical one for URDF arms)."""
    cl = cfg.closed_loop
    h = integrator_h(tau, cl.true_model_h if cl.true_model_h is not None else cfg.step.h)
    if cl.true_model_backend == "torch":
        return RK4Model(system, tau, h, str(cl.true_model_jacobian)), f"RK4 h={h:g}"
    if cl.true_model_backend == "compiled":
        return CompiledRK4(system, tau, h), f"RK4 h={h:g}, compiled"
    raise ValueError(f"closed_loop.true_model_backend={cl.true_model_backend!r}; expected 'torch' or 'compiled'")


def more_references(cfg: DictConfig) -> list[str]:
    """The built-ins tracked besides the main reference: as configured, else every one of the system's."""
    names = cfg.closed_loop.more_references
    return [str(n) for n in (cfg.system.references if names is None else names)]


def other_reference_row(cfg: DictConfig, system: System, surrogate: Surrogate, name: str) -> dict[str, Any]:
    """The configured controller on a built-in reference: tracking beyond the main trajectory; with
    offset-free MPC on, the MAE of the same controller without it too."""
    ref = bench_reference(cfg, system, surrogate.tau, name)
    solver = str(cfg.controller.solver)
    row, _ = run_controller(cfg, system, surrogate, ref, solver, record=False)
    if cfg.closed_loop.paper_controller and row["disturbance_gain"] > 0:
        plain, _ = run_controller(cfg, system, surrogate, ref, solver, record=False, disturbance=NO_DISTURBANCE)
        row["mae_without_disturbance"] = plain["mae"]
    log.info("closed loop: built-in reference %s done in %.1f s", name, row["wall_s"])
    return row


def mode(row: dict[str, Any], off: str = "") -> str:
    """Label suffix: whether the controller estimated a disturbance (offset-free MPC), else off."""
    gain = row["disturbance_gain"]
    return f", offset-free (gain {gain:g})" if gain > 0 else off


def _label(solver: str, row: dict[str, Any]) -> str:
    """Row label: the solver, a real-time iteration or not, and the controller mode."""
    fast = ", real-time iteration" if row.get("real_time") else ""
    return f"PINN-MPC, {solver}{fast}" + mode(row, ", paper's controller")
