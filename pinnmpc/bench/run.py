"""run_bench: the enabled sections in order, timed, then bench.json and bench.md written atomically."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import torch
from omegaconf import DictConfig, OmegaConf

from pinnmpc.bench.classical import CASADI_CONFIG, available, bench_classical, classical_plot
from pinnmpc.bench.common import bench_reference, optimality_solvers, paper_rows, timing_cfg
from pinnmpc.bench.floor import bench_floor
from pinnmpc.bench.kinds import bench_kinds
from pinnmpc.bench.loops import OCPProblem, bench_closed_loop, run_controller
from pinnmpc.bench.optimality import bench_optimality
from pinnmpc.bench.peers import bench_peers
from pinnmpc.bench.report import render_markdown
from pinnmpc.bench.robot import bench_robot
from pinnmpc.bench.scaling import bench_scaling
from pinnmpc.bench.settings import validate_bench
from pinnmpc.bench.step import bench_step
from pinnmpc.bench.targets import check_targets
from pinnmpc.bench.timing import machine_info
from pinnmpc.references.files import Reference
from pinnmpc.simulation.settings import within_plant_limits
from pinnmpc.surrogate.checkpoint import Surrogate, load_surrogate
from pinnmpc.systems.base import System
from pinnmpc.systems.registry import build_system
from pinnmpc.util.io import atomic_write, save_json
from pinnmpc.util.threads import use_threads

log = logging.getLogger(__name__)
T = TypeVar("T")


def load_pinn(cfg: DictConfig, system: System, dtype: torch.dtype = torch.float64) -> Surrogate:
    """checkpoint, or (null) the network shipped for this system, checked against the system's states."""
    shipped = system.name if cfg.checkpoint is None else None
    return load_surrogate(cfg.checkpoint, system=shipped, state_names=system.state_names, dtype=dtype)


def system_facts(system: System) -> dict[str, Any]:
    """Names, units and sizes of the system, for the report's headers."""
    return {
        "name": system.name,
        "tau": float(system.tau),
        "nq": int(system.nq),
        "state_names": list(system.state_names),
        "state_units": list(system.state_units),
        "input_names": list(system.input_names),
        "input_units": list(system.input_units),
    }


def run_bench(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Run the enabled sections; write bench.json, bench.md and plots into run_dir; return the JSON content."""
    run_dir = Path(run_dir)
    use_threads(cfg.threads)
    if cfg.controller.get("model", "surrogate") != "surrogate":
        raise ValueError(
            f"controller.model={cfg.controller.model!r}: the bench studies the surrogate's controller and adds the "
            "exact_values and prior rows to section 6 itself (classical.exact_values, classical.prior_alone); leave "
            "controller.model=surrogate"
        )
    system: System = build_system(cfg.system)
    validate_bench(cfg, system)
    within_plant_limits(cfg, system)
    names = tuple(system.state_names)
    pinn64 = load_pinn(cfg, system)
    kinds = cfg.get("kinds") is not None and cfg.kinds.enabled
    floor = cfg.get("floor") is not None and cfg.floor.enabled
    peers = cfg.get("peers") is not None and cfg.peers.enabled and available(cfg)
    need_ref = cfg.closed_loop.enabled or cfg.optimality.enabled or cfg.classical.enabled or kinds or floor or peers
    ref = bench_reference(cfg, system, pinn64.tau) if need_ref else None
    result: dict[str, Any] = {
        "machine": machine_info(),
        "system": system_facts(system),
        "paper": paper_rows(cfg, None if ref is None else ref.name),
        "config": OmegaConf.to_container(cfg, resolve=True),
    }
    elapsed: dict[str, float] = {}

    def timed(section: str, body: Callable[[], T]) -> T:
        """Run one section and keep its wall time."""
        t0 = time.perf_counter()
        out = body()
        elapsed[section] = time.perf_counter() - t0
        return out

    if cfg.step.enabled:
        pinn32 = load_pinn(cfg, system, torch.float32)
        result["step"] = timed("step", lambda: bench_step(cfg, system, pinn64, pinn32))
    problems: dict[str, list[OCPProblem]] = {}
    if cfg.closed_loop.enabled:
        result["closed_loop"], problems = timed("closed_loop", lambda: bench_closed_loop(cfg, system, pinn64, ref))
    if cfg.optimality.enabled:
        result["optimality"] = timed("optimality", lambda: optimality(cfg, system, pinn64, ref, problems))
    if cfg.scaling.enabled:
        result["scaling"] = timed("scaling", lambda: bench_scaling(cfg, system, pinn64, run_dir))
    if cfg.classical.enabled and not available(cfg):  # the hook: section 6 waits for the classical controller
        log.warning("classical: skipped, %s is absent", CASADI_CONFIG)
        result["classical"] = {"skipped": f"{CASADI_CONFIG} is absent"}
    elif cfg.classical.enabled:
        rows = result.get("closed_loop", {}).get("rows")
        result["classical"] = timed("classical", lambda: bench_classical(cfg, system, pinn64, ref, rows))
        if cfg.plots:
            classical_plot(result["classical"], system, run_dir / "classical.png")
    if cfg.get("robot") is not None and cfg.robot.enabled:
        result["robot"] = timed("robot", lambda: bench_robot(cfg, system, pinn64))
    if kinds:
        ran = [s for s in ("closed_loop", "classical") if s in result and "skipped" not in result[s]]
        result["kinds"] = timed("kinds", lambda: bench_kinds(cfg, system, ref, ran))
    if floor:
        result["floor"] = timed("floor", lambda: bench_floor(timing_cfg(cfg), system, pinn64, ref))
    if peers:
        result["peers"] = timed("peers", lambda: bench_peers(timing_cfg(cfg), system, pinn64, ref))
    elif cfg.get("peers") is not None and cfg.peers.enabled:  # the peers are the classical NMPC on the network
        log.warning("peers: skipped, %s is absent", CASADI_CONFIG)
        result["peers"] = {"skipped": f"{CASADI_CONFIG} is absent"}
    result["targets"] = check_targets(cfg, result, names)
    result["elapsed_s"] = {k: float(v) for k, v in elapsed.items()}
    save_json(run_dir / "bench.json", result)
    markdown = render_markdown(result)
    atomic_write(run_dir / "bench.md", lambda p: p.write_text(markdown))
    return result


def optimality(
    cfg: DictConfig, system: System, pinn64: Surrogate, ref: Reference, problems: dict[str, list[OCPProblem]]
) -> dict[str, Any]:
    """Section 3 for every examined solver, recording a closed loop first where section 2 did not run one."""
    out = {}
    for solver in optimality_solvers(cfg):
        if solver not in problems:  # no closed-loop row of this solver ran: record one
            _, problems[solver] = run_controller(cfg, system, pinn64, ref, solver, record=True)
        out[solver] = bench_optimality(cfg, pinn64, solver, problems[solver])
        log.info("optimality: %s done", solver)
    return out
