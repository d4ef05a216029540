"""`python -m pinnmpc.bench [overrides]`: the paper's cost and accuracy claims, measured properly on this machine.

Sections (each switchable in conf/bench.yaml):
1. one-step cost x_k -> x_k+1 of the PINN against Euler, RK4 and RK45, with the accuracy each one buys;
2. closed-loop tracking per solver, plus the same controller on an RK4 model of the true dynamics;
3. optimality: the gap of each solver's solutions to a tight multi-start L-BFGS-B reference solve;
4. scaling of OCP and one-step cost with horizon and batch size.
Writes bench.json, bench.md and PNG plots (all atomically) into the run dir and prints the markdown.
"""

from __future__ import annotations

import logging
import math
import os
import platform
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import hydra
import numpy as np
import scipy
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from scipy.optimize import minimize
from threadpoolctl import threadpool_info
from torch import Tensor

from pinnmpc.cli import run_cli
from pinnmpc.closed_loop import metrics, plant_system, simulate
from pinnmpc.controller.build import build_nmpc
from pinnmpc.controller.nmpc import NMPC
from pinnmpc.controller.ocp import Array, HorizonOCP
from pinnmpc.controller.solvers import SolveInfo, Solver
from pinnmpc.flow_numpy import NumpyFlow
from pinnmpc.integrators import euler_step, rk4_step
from pinnmpc.io import atomic_write, save_json
from pinnmpc.plant import ScipyPlant
from pinnmpc.references import Reference, load_reference, resolve_reference_path
from pinnmpc.surrogate import Dimensions, Surrogate, load_surrogate
from pinnmpc.systems.base import Box, System
from pinnmpc.threads import use_threads
from pinnmpc.training.data import random_pairs, reference_flow, uniform_box

log = logging.getLogger(__name__)

PERCENTILE = 95.0  # the "p95" of every table
STATUS_CHARS = 40  # a failed loop's status is cut to this many characters in its table cell
Model = Any  # Surrogate or RK4Model: anything with the interface HorizonOCP uses


# ---------------------------------------------------------------------------------------------------------------
# Machine and timing helpers


def cpu_model() -> str:
    """CPU name for the machine line: platform.processor() is empty on most Linux systems."""
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.exists():
        for line in cpuinfo.read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or "unknown CPU"


def machine_info() -> dict[str, Any]:
    """Where the numbers were measured: timings mean nothing without the machine and library versions."""
    return {
        "platform": platform.platform(),
        "cpu": cpu_model(),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "torch_threads": torch.get_num_threads(),
        "blas_threads": [(i["internal_api"], i["num_threads"]) for i in threadpool_info()],
        "load_average_1min": float(os.getloadavg()[0]) if hasattr(os, "getloadavg") else float("nan"),
    }


def time_calls(fn: Callable[[int], object], repeats: int, warmup: int) -> np.ndarray:
    """Wall times of fn(i) after untimed warm-up calls; i lets a call pick its own input."""
    for i in range(warmup):
        fn(i)
    times = np.empty(int(repeats))
    for i in range(int(repeats)):
        start = time.perf_counter()
        fn(i)
        times[i] = time.perf_counter() - start
    return times


def timing_stats(times: np.ndarray) -> dict[str, float]:
    """Median, mean and p95: the mean alone hides the heavy tail of adaptive solvers."""
    return {
        "median_s": float(np.median(times)),
        "mean_s": float(np.mean(times)),
        "p95_s": float(np.percentile(times, PERCENTILE)),
    }


def as_numpy(y: Tensor | np.ndarray) -> np.ndarray:
    """float64 numpy copy of any method's output, so errors are computed the same way for all."""
    if isinstance(y, Tensor):
        return y.detach().to(torch.float64).numpy()
    return np.asarray(y, dtype=np.float64)


# ---------------------------------------------------------------------------------------------------------------
# The true-model baseline: RK4 of the physics behind the Surrogate interface


class RK4Model(Dimensions):
    """The true dynamics integrated by RK4 behind the Surrogate interface: the controller's perfect-model baseline."""

    def __init__(self, system: System, tau: float, h: float, jacobian: str = "reverse") -> None:
        if jacobian not in ("reverse", "jacfwd"):
            raise ValueError(f"unknown jacobian mode {jacobian!r}; expected 'reverse' or 'jacfwd'")
        self.system = system
        self.tau, self.h, self.jacobian = float(tau), float(h), jacobian
        self.dtype = torch.float64
        self.state_names, self.input_names = tuple(system.state_names), tuple(system.input_names)
        self.state_box: Box = system.state_box
        self.input_box: Box = system.input_box
        nx = len(self.state_names)
        self.domain = Box([-math.inf] * nx, [math.inf] * nx)  # the physics holds for every state
        self._jacfwd = torch.func.vmap(torch.func.jacfwd(self._flow_with_aux, argnums=(0, 1), has_aux=True))

    def _flow(self, x0: Tensor, u: Tensor) -> Tensor:
        """x(tau) by RK4 with step h over the torch rhs."""
        return rk4_step(self.system.rhs, x0, u, self.tau, self.h)

    def _flow_with_aux(self, x0: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """The flow twice: jacfwd differentiates the first and hands back the second as the value."""
        x1 = self._flow(x0, u)
        return x1, x1

    def step(self, x0: Tensor, u: Tensor) -> Tensor:
        """x(tau): one zero-hold sampling period."""
        return self._flow(x0.to(self.dtype), u.to(self.dtype))

    def step_with_jacobian(self, x0: Tensor, u: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """x(tau), A = dx/dx0 (..., nx, nx) and B = dx/du (..., nx, nu), exact (autodiff through RK4)."""
        lead, nx, nu = x0.shape[:-1], self.nx, self.nu
        xf, uf = x0.to(self.dtype).reshape(-1, nx), u.to(self.dtype).reshape(-1, nu)
        if self.jacobian == "jacfwd":
            (A, B), x1 = self._jacfwd(xf, uf)
        else:
            x1, A, B = self._reverse_jacobian(xf, uf)
        return x1.reshape(*lead, nx), A.reshape(*lead, nx, nx), B.reshape(*lead, nx, nu)

    def _reverse_jacobian(self, x0: Tensor, u: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """One reverse pass over nx copies of the batch, row i seeded with e_i: ~10x cheaper than functorch jvp."""
        nx, nu = self.nx, self.nu
        with torch.enable_grad():
            xr = x0.detach().unsqueeze(-2).expand(-1, nx, nx).clone().requires_grad_(True)
            ur = u.detach().unsqueeze(-2).expand(-1, nx, nu).clone().requires_grad_(True)
            y = self._flow(xr, ur)
            seed = torch.eye(nx, dtype=y.dtype).expand_as(y)
            A, B = torch.autograd.grad(y, (xr, ur), seed)
        return y.detach()[:, 0], A, B


# ---------------------------------------------------------------------------------------------------------------
# 1. One-step cost and accuracy


@dataclass(frozen=True)
class StepMethod:
    """One way to compute x_k+1 from x_k; inputs are converted outside the timed call, so only the step is timed."""

    key: str
    label: str
    paper: str  # key into cfg.paper.step_mean_s
    prepare: Callable[[np.ndarray, np.ndarray], tuple[Any, ...]]
    call: Callable[..., Any]
    vectorised: bool = True


def _numpy_inputs(x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Contiguous float64 copies for the numpy integrators and the scipy plant."""
    return np.ascontiguousarray(x, dtype=np.float64), np.ascontiguousarray(u, dtype=np.float64)


def _torch_inputs(dtype: torch.dtype) -> Callable[[np.ndarray, np.ndarray], tuple[Tensor, Tensor]]:
    """Converter to torch tensors of the given dtype."""

    def convert(x: np.ndarray, u: np.ndarray) -> tuple[Tensor, Tensor]:
        return torch.from_numpy(x).to(dtype).contiguous(), torch.from_numpy(u).to(dtype).contiguous()

    return convert


def _rk45_loop(plant: ScipyPlant, x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The plant has no batch: one solve_ivp per sample, as anyone using RK45 for a batch would have to."""
    return np.stack([plant.step(xi, ui) for xi, ui in zip(x, u)])


def step_methods(system: System, pinn64: Surrogate, pinn32: Surrogate, plant: ScipyPlant, h: float) -> list[StepMethod]:
    """Every row of the one-step table: the PINN in two precisions, fixed-step baselines in numpy and torch, RK45."""
    tau = pinn64.tau
    pinn_numpy = NumpyFlow.from_pinn(pinn64.model, tau)  # what the Gauss-Newton controller evaluates
    euler = partial(euler_step, system.rhs, tau=tau, h=h)
    rk4 = partial(rk4_step, system.rhs, tau=tau, h=h)
    return [
        StepMethod("pinn_f64", "PINN float64 (torch)", "pinn", _torch_inputs(torch.float64), pinn64.step),
        StepMethod("pinn_f32", "PINN float32 (torch)", "pinn", _torch_inputs(torch.float32), pinn32.step),
        StepMethod("pinn_numpy", "PINN float64 (numpy fast path)", "pinn", _numpy_inputs, pinn_numpy.step),
        StepMethod("euler_numpy", f"Euler h={h:g} (numpy)", "euler", _numpy_inputs, euler),
        StepMethod("euler_torch", f"Euler h={h:g} (torch)", "euler", _torch_inputs(torch.float64), euler),
        StepMethod("rk4_numpy", f"RK4 h={h:g} (numpy)", "rk4", _numpy_inputs, rk4),
        StepMethod("rk4_torch", f"RK4 h={h:g} (torch)", "rk4", _torch_inputs(torch.float64), rk4),
        StepMethod(
            "rk45", "RK45 (scipy solve_ivp)", "rk45", _numpy_inputs, partial(_rk45_loop, plant), vectorised=False
        ),
    ]


def random_states(system: System, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """x0 uniform in the state box and u uniform in the input box (the training box), seeded."""
    x0, u = random_pairs(system, n, seed)
    return x0.numpy(), u.numpy()


def time_method(method: StepMethod, x: np.ndarray, u: np.ndarray, batch: int, repeats: int, warmup: int) -> np.ndarray:
    """Timings at one batch size; batch 1 cycles through the states, since RK45's cost depends on the state."""
    if batch == 1:
        n = min(len(x), repeats + warmup)
        args = [method.prepare(x[i : i + 1], u[i : i + 1]) for i in range(n)]
        return time_calls(lambda i: method.call(*args[i % n]), repeats, warmup)
    batch_args = method.prepare(x[:batch], u[:batch])
    return time_calls(lambda _i: method.call(*batch_args), repeats, warmup)


def bench_step(cfg: DictConfig, system: System, pinn64: Surrogate, pinn32: Surrogate) -> dict[str, Any]:
    """Table 1 done right: median/mean/p95 per batch size, and the one-step RMSE each method buys."""
    sc = cfg.step
    if sc.rk45_batch not in ("loop", "skip"):
        raise ValueError(f"step.rk45_batch={sc.rk45_batch!r}; expected 'loop' or 'skip'")
    batches = [int(b) for b in sc.batch_sizes]
    plant = ScipyPlant(plant_system(system, cfg.plant), pinn64.tau, cfg.plant.method, cfg.plant.rtol, cfg.plant.atol)
    methods = step_methods(system, pinn64, pinn32, plant, float(sc.h))
    x, u = random_states(system, max(int(sc.n_states), *batches), int(cfg.seed))
    xs, us = x[: int(sc.n_states)], u[: int(sc.n_states)]
    x_ref = reference_flow(system, torch.from_numpy(xs), torch.from_numpy(us), pinn64.tau, float(sc.ref_h)).numpy()
    rmse: dict[str, dict[str, float]] = {}
    timing: dict[str, dict[str, dict[str, float]]] = {}
    rk45_median: dict[str, float] = {}
    with torch.inference_mode():
        for m in methods:
            err = as_numpy(m.call(*m.prepare(xs, us))) - x_ref
            rmse[m.key] = {n: float(v) for n, v in zip(system.state_names, np.sqrt(np.mean(err**2, axis=0)))}
        for b in batches:
            rows: dict[str, dict[str, float]] = {}
            for m in methods:
                if m.vectorised or b == 1:
                    times = time_method(m, x, u, b, int(sc.repeats), int(sc.warmup))
                elif sc.rk45_batch == "loop":
                    times = time_method(m, x, u, b, int(sc.rk45_loop_repeats), 0)
                else:
                    continue
                rows[m.key] = {**timing_stats(times), "per_sample_median_s": float(np.median(times)) / b}
            if "rk45" in rows:
                rk45_median[str(b)] = rows["rk45"]["median_s"]
                for row in rows.values():
                    row["ratio_to_rk45"] = row["median_s"] / rk45_median[str(b)]
            timing[str(b)] = rows
            log.info("step: batch %d timed", b)
    return {
        "tau_s": pinn64.tau,
        "h_s": float(sc.h),
        "ref_h_s": float(sc.ref_h),
        "n_states": int(sc.n_states),
        "repeats": int(sc.repeats),
        "warmup": int(sc.warmup),
        "rk45_batch": str(sc.rk45_batch),
        "rk45_loop_repeats": int(sc.rk45_loop_repeats),
        "methods": {m.key: {"label": m.label, "paper": m.paper} for m in methods},
        "rmse": rmse,
        "timing": timing,
        "rk45_median_s": rk45_median,
    }


# ---------------------------------------------------------------------------------------------------------------
# 2. Closed loop


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
        return getattr(self.inner, "array_api", "torch")

    @property
    def accepts_prior(self) -> bool:
        """Whether the wrapped solver takes a warm start beyond U0."""
        return getattr(self.inner, "accepts_prior", False)

    @property
    def prior_kind(self) -> str:
        """The SolveInfo field the wrapped solver takes as that warm start."""
        return getattr(self.inner, "prior_kind", "sensitivities")

    def solve(
        self,
        ocp: HorizonOCP,
        x0: Array,
        U0: Array,
        x_ref: Array,
        u_prev: Array,
        low: Array,
        high: Array,
        **options: Any,
    ) -> tuple[Array, SolveInfo]:
        """Delegate, then record each problem of the batch with its projected solution."""
        U, info = self.inner.solve(ocp, x0, U0, x_ref, u_prev, low, high, **options)
        Uc = np.clip(np.asarray(U, dtype=np.float64), np.asarray(low), np.asarray(high))
        d = np.zeros(ocp.nx) if ocp.disturbance is None else ocp.disturbance
        for i in range(x0.shape[0]):
            self.raw.append(tuple(as_numpy(a).copy() for a in (x0[i], x_ref[i], u_prev[i], Uc[i], d)))
        return U, info


NO_DISTURBANCE = {"gain": 0.0}  # controller.disturbance override: the paper's controller, no offset-free MPC


def controller_cfg(cfg: DictConfig, **changes: Any) -> DictConfig:
    """The controller section with a few settings swapped (solver, horizon), everything else as configured."""
    return OmegaConf.merge(cfg.controller, changes)


def run_controller(
    cfg: DictConfig, system: System, model: Model, ref: Reference, solver: str, record: bool, **changes: Any
) -> tuple[dict[str, Any], list[OCPProblem]]:
    """One closed loop on the RK45 plant; the row of the table and, when asked, the OCPs it solved."""
    nmpc: NMPC = build_nmpc(controller_cfg(cfg, solver=solver, **changes), model)
    recorder = RecordingSolver(nmpc.solver) if record else None
    if recorder is not None:
        nmpc.solver = recorder
    plant = ScipyPlant(plant_system(system, cfg.plant), model.tau, cfg.plant.method, cfg.plant.rtol, cfg.plant.atol)
    start = time.perf_counter()
    run = simulate(nmpc, plant, ref, 0.0, int(cfg.seed), cfg.closed_loop.max_steps, bool(cfg.progress))
    wall = time.perf_counter() - start
    m = metrics(ref, run, nmpc, plant, system.state_names)
    ocp = m["ocp_time_s"]
    row = {
        "solver": solver,
        "disturbance_gain": float(nmpc.disturbance_gain),
        "status": m["status"],
        "steps": int(m["steps"]),
        "mae": m["mae"],
        "ocp_time_s": {"mean": ocp["mean"], "median": ocp["median"], "p95": ocp["p95"], "max": ocp["max"]},
        "plant_step_median_s": m["plant_step_time_s"]["median"],
        "ratio_ocp_to_plant": ocp["median"] / m["plant_step_time_s"]["median"],
        "iterations_mean": float(m["iterations"]["mean"]),
        "converged_fraction": float(m["converged_fraction"]),
        "fallbacks": int(m["fallbacks"]),
        "out_of_box_steps": int(m["out_of_box_steps"]),
        "wall_s": float(wall),
    }
    return row, (recorder.problems if recorder is not None else [])


def optimality_solvers(cfg: DictConfig) -> list[str]:
    """The solvers whose OCPs the optimality section re-solves: as configured, or every PINN row of section 2."""
    chosen = cfg.optimality.solvers
    if chosen is None:
        chosen = cfg.closed_loop.solvers if cfg.closed_loop.enabled else [cfg.controller.solver]
    return [str(s) for s in chosen]


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
        model = RK4Model(system, surrogate.tau, float(cl.true_model_h), str(cl.true_model_jacobian))
        for solver in cl.true_model_solvers:
            row, _ = run_controller(cfg, system, model, ref, solver, record=False)
            label = f"true model (RK4 h={float(cl.true_model_h):g}), {solver}"
            rows[f"true_rk4_{solver}"] = {"label": label, "model": "rk4", **row}
            log.info("closed loop: true model %s done in %.1f s", solver, row["wall_s"])
    others = {name: other_reference_row(cfg, system, surrogate, name) for name in cl.more_references}
    result = {"reference": ref.name, "horizon": int(cfg.controller.horizon), "rows": rows, "references": others}
    return result, problems


def other_reference_row(cfg: DictConfig, system: System, surrogate: Surrogate, name: str) -> dict[str, Any]:
    """The configured controller on a built-in reference: tracking beyond the paper's one trajectory; with
    offset-free MPC on, the MAE of the same controller without it too."""
    ref = load_reference(None, surrogate.tau, name)
    solver = str(cfg.controller.solver)
    row, _ = run_controller(cfg, system, surrogate, ref, solver, record=False)
    if cfg.closed_loop.paper_controller and row["disturbance_gain"] > 0:
        plain, _ = run_controller(cfg, system, surrogate, ref, solver, record=False, disturbance=NO_DISTURBANCE)
        row["mae_without_disturbance"] = plain["mae"]
    log.info("closed loop: built-in reference %s done in %.1f s", name, row["wall_s"])
    return row


def _mode(row: dict[str, Any], off: str = "") -> str:
    """Label suffix: whether the controller estimated a disturbance (offset-free MPC), else off."""
    gain = row["disturbance_gain"]
    return f", offset-free (gain {gain:g})" if gain > 0 else off


def _label(solver: str, row: dict[str, Any]) -> str:
    """Row label: the solver and the controller mode."""
    return f"PINN-MPC, {solver}" + _mode(row, ", paper's controller")


# ---------------------------------------------------------------------------------------------------------------
# 3. Optimality of the Gauss-Newton solutions


def lbfgsb_solve(
    ocp: HorizonOCP, p: OCPProblem, start: np.ndarray, bounds: list[tuple[float, float]], oc: DictConfig
) -> tuple[float, int]:
    """Tight scipy L-BFGS-B on the same surrogate with autograd gradients; the final cost and iteration count."""
    shape = (1, ocp.horizon, ocp.nu)
    x0, x_ref, u_prev = p.x0[None], p.x_ref[None], p.u_prev[None]

    def fun(z: np.ndarray) -> tuple[float, np.ndarray]:
        U = torch.from_numpy(z).reshape(shape).requires_grad_(True)
        cost = ocp.cost(x0, U, x_ref, u_prev).sum()
        (grad,) = torch.autograd.grad(cost, U)
        return float(cost.detach()), grad.numpy().ravel()

    opts = {"ftol": float(oc.ftol), "gtol": float(oc.gtol), "maxiter": int(oc.maxiter)}
    res = minimize(fun, start, jac=True, method="L-BFGS-B", bounds=bounds, options=opts)
    with torch.no_grad():
        final = float(ocp.cost(x0, torch.from_numpy(res.x).reshape(shape), x_ref, u_prev).sum())
    return final, int(res.nit)


def bench_optimality(cfg: DictConfig, surrogate: Surrogate, solver: str, problems: list[OCPProblem]) -> dict[str, Any]:
    """How far one solver's solutions are from the best of several tight L-BFGS-B solves of the same OCPs."""
    oc = cfg.optimality
    if not problems:
        raise ValueError(f"optimality needs OCPs from a {solver} closed loop; none were recorded")
    nmpc = build_nmpc(controller_cfg(cfg, solver=solver), surrogate)
    ocp, low, high = nmpc.ocp, nmpc.low.numpy(), nmpc.high.numpy()
    H = ocp.horizon
    bounds = list(zip(np.tile(low, H).tolist(), np.tile(high, H).tolist()))
    n = min(int(oc.n_states), len(problems))
    picks = np.unique(np.linspace(0, len(problems) - 1, n).round().astype(int))
    rng = np.random.default_rng(int(cfg.seed))
    gn, best, nits, best_start = [], [], [], []
    start_names = ["zeros", solver, *[f"random{i}" for i in range(int(oc.random_starts))]]
    t0 = time.perf_counter()
    for i in picks:
        p = problems[int(i)]
        ocp.disturbance = p.disturbance.numpy()  # the very problem the controller solved
        with torch.no_grad():
            gn.append(float(ocp.cost(p.x0[None], p.U[None], p.x_ref[None], p.u_prev[None]).sum()))
        starts = [np.clip(np.zeros(H * ocp.nu), np.tile(low, H), np.tile(high, H)), p.U.numpy().ravel().copy()]
        starts += [rng.uniform(np.tile(low, H), np.tile(high, H)) for _ in range(int(oc.random_starts))]
        results = [lbfgsb_solve(ocp, p, s, bounds, oc) for s in starts]
        costs = [c for c, _ in results]
        nits.extend(it for _, it in results)
        best.append(min(costs))
        best_start.append(start_names[int(np.argmin(costs))])
    gn_a, ref_a = np.array(gn), np.array(best)
    gap_abs = gn_a - ref_a
    gap = gap_abs / np.maximum(ref_a, float(oc.cost_floor))
    within = (gap <= float(oc.rel_tol)) | (gap_abs <= float(oc.abs_tol))
    return {
        "solver": solver,
        "n_states": len(picks),
        "starts": start_names,
        "rel_gap": {
            "median": float(np.median(gap)),
            "p95": float(np.percentile(gap, PERCENTILE)),
            "max": float(np.max(gap)),
            "min": float(np.min(gap)),
        },
        "abs_gap_max": float(np.max(gap_abs)),
        "fraction_within": float(np.mean(within)),
        "rel_tol": float(oc.rel_tol),
        "abs_tol": float(oc.abs_tol),
        "ftol": float(oc.ftol),
        "gtol": float(oc.gtol),
        "maxiter": int(oc.maxiter),
        "gn_cost_median": float(np.median(gn_a)),
        "ref_cost_median": float(np.median(ref_a)),
        "best_start_counts": {s: best_start.count(s) for s in start_names},
        "lbfgsb_iterations_mean": float(np.mean(nits)),
        "lbfgsb_iterations_max": int(np.max(nits)),
        "wall_s": float(time.perf_counter() - t0),
    }


# ---------------------------------------------------------------------------------------------------------------
# 4. Scaling


def ocp_scaling_point(cfg: DictConfig, surrogate: Surrogate, horizon: int, batch: int) -> dict[str, float]:
    """Batched solves by the configured solver of random problems (states and references uniform in the box)."""
    sc = cfg.scaling
    nmpc = build_nmpc(controller_cfg(cfg, horizon=horizon), surrogate)
    box, nx, nu = surrogate.state_box, surrogate.nx, surrogate.nu
    seed = int(cfg.seed)
    x0 = uniform_box(batch, box.low, box.high, seed)
    x_ref = uniform_box(batch * horizon, box.low, box.high, seed + 1).reshape(batch, horizon, nx)
    U0 = torch.zeros(batch, horizon, nu, dtype=torch.float64).clamp(nmpc.low, nmpc.high)
    u_prev = U0[:, 0].clone()
    iters: list[float] = []

    def solve(_i: int) -> None:
        _, info = nmpc.solve(x0, x_ref, U0, u_prev)
        iters.append(float(info.iterations.double().mean()))

    times = time_calls(solve, int(sc.repeats), int(sc.warmup))
    med = float(np.median(times))
    return {
        "horizon": horizon,
        "batch": batch,
        **timing_stats(times),
        "per_problem_median_s": med / batch,
        "problems_per_s": batch / med,
        "iterations_mean": float(np.mean(iters)),
    }


def step_scaling(cfg: DictConfig, system: System, surrogate: Surrogate) -> dict[str, list[float]]:
    """One-step cost vs batch size for the PINN and torch RK4: where batching pays off."""
    sc = cfg.scaling
    batches = [int(b) for b in sc.step_batch_sizes]
    x, u = random_states(system, max(batches), int(cfg.seed))
    methods = {
        "pinn_f64": (surrogate.step, _torch_inputs(torch.float64)),
        "rk4_torch": (
            partial(rk4_step, system.rhs, tau=surrogate.tau, h=float(cfg.step.h)),
            _torch_inputs(torch.float64),
        ),
    }
    out: dict[str, list[float]] = {"batch_sizes": [float(b) for b in batches]}
    with torch.inference_mode():
        for key, (call, prepare) in methods.items():
            medians = []
            for b in batches:
                args = prepare(x[:b], u[:b])
                medians.append(
                    float(
                        np.median(
                            time_calls(lambda _i, a=args, c=call: c(*a), int(sc.step_repeats), int(sc.step_warmup))
                        )
                    )
                )
            out[f"{key}_median_s"] = medians
            out[f"{key}_per_sample_s"] = [m / b for m, b in zip(medians, batches)]
    return out


def bench_scaling(cfg: DictConfig, system: System, surrogate: Surrogate, run_dir: Path) -> dict[str, Any]:
    """OCP time vs horizon and batch size, one-step cost vs batch size, with a plot of each."""
    sc = cfg.scaling
    base_h = int(sc.base_horizon if sc.base_horizon is not None else cfg.controller.horizon)
    horizon_rows = [ocp_scaling_point(cfg, surrogate, int(h), int(sc.base_batch)) for h in sc.horizons]
    batch_rows = [ocp_scaling_point(cfg, surrogate, base_h, int(b)) for b in sc.batch_sizes]
    steps = step_scaling(cfg, system, surrogate)
    plots_written = []
    if cfg.plots:
        from pinnmpc import plots

        figures = {
            "scaling_horizon.png": plots.scaling_figure(
                [r["horizon"] for r in horizon_rows],
                {f"time per solve (B={int(sc.base_batch)})": [r["median_s"] for r in horizon_rows]},
                "horizon H [steps]",
                "median time [s]",
                "Gauss-Newton OCP solve vs horizon",
            ),
            "scaling_batch.png": plots.scaling_figure(
                [r["batch"] for r in batch_rows],
                {
                    "time per batched solve": [r["median_s"] for r in batch_rows],
                    "time per problem": [r["per_problem_median_s"] for r in batch_rows],
                },
                "batch size B [problems]",
                "median time [s]",
                f"Gauss-Newton OCP solve vs batch size (H={base_h})",
            ),
            "scaling_step.png": plots.scaling_figure(
                steps["batch_sizes"],
                {
                    "PINN float64, per call": steps["pinn_f64_median_s"],
                    "RK4 torch, per call": steps["rk4_torch_median_s"],
                    "PINN float64, per sample": steps["pinn_f64_per_sample_s"],
                    "RK4 torch, per sample": steps["rk4_torch_per_sample_s"],
                },
                "batch size [states]",
                "median time [s]",
                "one step x_k -> x_k+1 vs batch size",
            ),
        }
        for name, fig in figures.items():
            plots.save_figure(fig, run_dir / name)
            plots_written.append(name)
    return {
        "base_horizon": base_h,
        "base_batch": int(sc.base_batch),
        "horizon": horizon_rows,
        "batch": batch_rows,
        "step": steps,
        "plots": plots_written,
    }


# ---------------------------------------------------------------------------------------------------------------
# Markdown


def fmt(value: float | int | str | None, spec: str = ".3g") -> str:
    """Table cell: numbers compact, missing values as a dash."""
    if value is None:
        return "—"
    if isinstance(value, str):
        return value
    if isinstance(value, int):
        return str(value)
    return format(value, spec)


def md_table(headers: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """A GitHub-flavoured markdown table."""
    lines = ["| " + " | ".join(headers) + " |", "|" + "|".join("---" for _ in headers) + "|"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def machine_line(m: dict[str, Any]) -> str:
    """One line naming the machine, so nobody compares timings from different boxes unknowingly."""
    return (
        f"Machine: {m['platform']}, {m['cpu']}, {m['cpu_count']} CPUs, Python {m['python']}, torch {m['torch']}, "
        f"numpy {m['numpy']}, scipy {m['scipy']}, torch threads {m['torch_threads']}, "
        f"1-min load average at start {m['load_average_1min']:.2f}."
    )


def md_step(step: dict[str, Any], paper: dict[str, Any], names: Sequence[str]) -> str:
    """Section 1 tables: timing per batch size with the paper's numbers, then the accuracy table."""
    out = [
        "## 1. One-step cost x_k -> x_k+1 (Table 1 done right)",
        "",
        f"tau = {step['tau_s']:g} s; Euler/RK4 step h = {step['h_s']:g} s; {step['repeats']} timed calls after "
        f"{step['warmup']} warm-up calls; batch 1 cycles through {step['n_states']} random states in the training box. "
        f"Ratio: median / RK45 median at the same batch size, this run. RK45 at batch > 1: "
        + (
            f"a per-sample loop of solve_ivp, {step['rk45_loop_repeats']} timed loops."
            if step["rk45_batch"] == "loop"
            else "skipped (solve_ivp has no batch)."
        ),
        "",
    ]
    for b, rows in step["timing"].items():
        table = []
        for key, r in rows.items():
            meta = step["methods"][key]
            pkey = meta["paper"]
            paper_mean = paper["step_mean_s"].get(pkey) if b == "1" else None
            paper_median = paper["step_median_s"].get(pkey) if b == "1" else None
            table.append(
                [
                    meta["label"],
                    fmt(r["median_s"], ".3e"),
                    fmt(r["mean_s"], ".3e"),
                    fmt(r["p95_s"], ".3e"),
                    fmt(r["per_sample_median_s"], ".3e"),
                    fmt(r.get("ratio_to_rk45")),
                    fmt(paper_mean, ".2e"),
                    fmt(paper_median, ".2e"),
                ]
            )
        headers = [
            "method",
            "median [s]",
            "mean [s]",
            "p95 [s]",
            "median per sample [s]",
            "/ RK45 median",
            "paper mean [s]",
            "paper median [s]",
        ]
        out += [f"### batch {b}", "", md_table(headers, table), ""]
    acc = [[step["methods"][k]["label"], *(fmt(v[n], ".2e") for n in names)] for k, v in step["rmse"].items()]
    out += [
        f"### one-step RMSE vs fine RK4 (h = {step['ref_h_s']:g} s), {step['n_states']} random states",
        "",
        md_table(["method", *(f"RMSE {n}" for n in names)], acc),
        "",
    ]
    return "\n".join(out)


def md_closed_loop(
    cl: dict[str, Any], paper: dict[str, Any], names: Sequence[str], optimality: dict[str, Any] | None = None
) -> str:
    """Section 2 table: tracking error, solve cost and optimality gap per controller, with the paper's row."""
    optimality = optimality or {}
    headers = [
        "controller",
        *(f"MAE {n}" for n in names),
        "OCP mean [s]",
        "OCP median [s]",
        "OCP p95 [s]",
        "OCP median / plant step median",
        "iterations mean",
        "optimality rel gap max",
        "fallbacks",
        "steps",
    ]
    rows = []
    for r in cl["rows"].values():
        rows.append(
            [
                r["label"] + ("" if r["status"] == "ok" else f" ({r['status'][:STATUS_CHARS]})"),
                *(fmt(r["mae"][n], ".2e") for n in names),
                fmt(r["ocp_time_s"]["mean"], ".2e"),
                fmt(r["ocp_time_s"]["median"], ".2e"),
                fmt(r["ocp_time_s"]["p95"], ".2e"),
                fmt(r["ratio_ocp_to_plant"]),
                fmt(r["iterations_mean"], ".1f"),
                _gap_cell(r, optimality),
                fmt(r["fallbacks"]),
                fmt(r["steps"]),
            ]
        )
    pc = paper["closed_loop"]
    rows.append(
        [
            "paper (RMSprop, TensorFlow, M1)",
            *(fmt(pc["mae"].get(n), ".2e") for n in names),
            fmt(pc["ocp_mean_s"], ".2e"),
            *["—"] * 7,
        ]
    )
    return "\n".join(
        [
            "## 2. Closed loop",
            "",
            f"Reference: {cl['reference']}; horizon {cl['horizon']}; plant RK45; MAE in rad and rad/s. "
            "The true-model rows run the same controller on an RK4 model of the physics "
            "(exact Jacobians by autodiff through RK4). Optimality gap: section 3.",
            "",
            md_table(headers, rows),
            "",
        ]
    )


def md_other_references(cl: dict[str, Any], names: Sequence[str]) -> str:
    """Section 2 sub-table: the configured controller on the built-in references."""
    headers = [
        "reference",
        "solver",
        "steps",
        *(f"MAE {n}" for n in names),
        "OCP median [s]",
        "OCP p95 [s]",
        "OCP median / plant step median",
        "iterations mean",
        "fallbacks",
    ]
    plain = any("mae_without_disturbance" in r for r in cl["references"].values())
    if plain:
        headers[3:3] = [f"MAE {n} without offset-free" for n in names]
    rows = [
        [
            name + ("" if r["status"] == "ok" else f" ({r['status'][:STATUS_CHARS]})"),
            r["solver"] + _mode(r),
            fmt(r["steps"]),
            *((fmt(r.get("mae_without_disturbance", {}).get(n), ".2e") for n in names) if plain else ()),
            *(fmt(r["mae"][n], ".2e") for n in names),
            fmt(r["ocp_time_s"]["median"], ".2e"),
            fmt(r["ocp_time_s"]["p95"], ".2e"),
            fmt(r["ratio_ocp_to_plant"]),
            fmt(r["iterations_mean"], ".1f"),
            fmt(r["fallbacks"]),
        ]
        for name, r in cl["references"].items()
    ]
    return "\n".join(["### Built-in references", "", md_table(headers, rows), ""])


def _gap_cell(row: dict[str, Any], optimality: dict[str, Any]) -> str:
    """The worst relative optimality gap of a PINN row's solver (section 3), or a dash when not examined."""
    op = optimality.get(row["solver"]) if row["model"] == "pinn" else None
    return "—" if op is None else fmt(op["rel_gap"]["max"], ".1e")


def md_optimality(per_solver: dict[str, dict[str, Any]]) -> str:
    """Section 3 table: the gap distribution of each solver to the L-BFGS-B reference."""
    rows = [_optimality_row(op) for op in per_solver.values()]
    op = next(iter(per_solver.values()))
    headers = [
        "solver",
        "OCPs",
        "rel gap median",
        "rel gap p95",
        "rel gap max",
        "abs gap max",
        "fraction optimal",
        "best start (count)",
        "L-BFGS-B iterations mean",
    ]
    return "\n".join(
        [
            "## 3. OCP optimality",
            "",
            "States visited by each solver's closed loop of section 2; each OCP re-solved on the same surrogate by "
            f"scipy L-BFGS-B (ftol {op['ftol']:g}, gtol {op['gtol']:g}, maxiter {op['maxiter']}, autograd gradient) "
            "from zeros, the solver's own solution and random starts. "
            "rel gap = (solver's cost - best cost) / best cost; "
            f"optimal: rel gap <= {op['rel_tol']:g} or abs gap <= {op['abs_tol']:g}.",
            "",
            md_table(headers, rows),
            "",
        ]
    )


def _optimality_row(op: dict[str, Any]) -> list[str]:
    """One solver's row of the optimality table."""
    g = op["rel_gap"]
    return [
        op["solver"],
        fmt(op["n_states"]),
        fmt(g["median"], ".2e"),
        fmt(g["p95"], ".2e"),
        fmt(g["max"], ".2e"),
        fmt(op["abs_gap_max"], ".2e"),
        fmt(op["fraction_within"]),
        ", ".join(f"{k} {v}" for k, v in op["best_start_counts"].items()),
        fmt(op["lbfgsb_iterations_mean"], ".1f"),
    ]


def md_scaling(sc: dict[str, Any]) -> str:
    """Section 4 tables: OCP time vs horizon and batch size, one-step cost vs batch size."""

    def ocp_rows(rows: list[dict[str, Any]]) -> list[list[str]]:
        return [
            [
                fmt(r["horizon"]),
                fmt(r["batch"]),
                fmt(r["median_s"], ".2e"),
                fmt(r["p95_s"], ".2e"),
                fmt(r["per_problem_median_s"], ".2e"),
                fmt(r["problems_per_s"], ".3g"),
                fmt(r["iterations_mean"], ".1f"),
            ]
            for r in rows
        ]

    headers = ["H", "B", "median per solve [s]", "p95 [s]", "per problem [s]", "problems/s", "iterations mean"]
    st = sc["step"]
    step_rows = [
        [fmt(int(b)), fmt(p, ".2e"), fmt(pp, ".2e"), fmt(r, ".2e"), fmt(rp, ".2e")]
        for b, p, pp, r, rp in zip(
            st["batch_sizes"],
            st["pinn_f64_median_s"],
            st["pinn_f64_per_sample_s"],
            st["rk4_torch_median_s"],
            st["rk4_torch_per_sample_s"],
        )
    ]
    return "\n".join(
        [
            "## 4. Scaling",
            "",
            "Batched NMPC.solve (the configured solver) on random states and references (uniform in the training box), "
            "zero start.",
            "",
            f"### OCP vs horizon (B = {sc['base_batch']})",
            "",
            md_table(headers, ocp_rows(sc["horizon"])),
            "",
            f"### OCP vs batch size (H = {sc['base_horizon']})",
            "",
            md_table(headers, ocp_rows(sc["batch"])),
            "",
            "### one step vs batch size (median)",
            "",
            md_table(["B", "PINN f64 [s]", "PINN per sample [s]", "RK4 torch [s]", "RK4 per sample [s]"], step_rows),
            "",
            "Plots: " + (", ".join(sc["plots"]) or "off"),
            "",
        ]
    )


# ---------------------------------------------------------------------------------------------------------------
# 5. Targets


def _target(what: str, value: float, limit: float) -> dict[str, Any]:
    """One target: met when the measured value is at most the limit."""
    return {"what": what, "value": float(value), "limit": float(limit), "met": bool(value <= limit)}


def check_targets(cfg: DictConfig, result: dict[str, Any], names: Sequence[str]) -> list[dict[str, Any]]:
    """The project's targets next to this run's numbers, for the sections that ran."""
    t = cfg.targets
    rows = []
    if "step" in result:
        rmse = result["step"]["rmse"]["pinn_numpy"]
        rows += [_target(f"one-step RMSE {n}", rmse[n], lim) for n, lim in zip(names, t.one_step_rmse) if lim]
    row = result.get("closed_loop", {}).get("rows", {}).get(f"pinn_{cfg.controller.solver}")
    if row is not None:
        where = f"closed loop on {result['closed_loop']['reference']}"
        rows += [_target(f"{where}: MAE {n}", row["mae"][n], lim) for n, lim in zip(names, t.closed_loop_mae) if lim]
        rows.append(_target("OCP median / plant step median", row["ratio_ocp_to_plant"], t.ocp_median_ratio))
        p95_ratio = row["ocp_time_s"]["p95"] / row["plant_step_median_s"]
        rows.append(_target("OCP p95 / plant step median", p95_ratio, t.ocp_p95_ratio))
    return rows


def md_targets(targets: list[dict[str, Any]]) -> str:
    """Section 5 table: target, limit, this run, met or not."""
    rows = [
        [r["what"], fmt(r["limit"], ".3g"), fmt(r["value"], ".3g"), "yes" if r["met"] else "**no**"] for r in targets
    ]
    return "\n".join(["## 5. Targets", "", md_table(["target", "limit", "this run", "met"], rows), ""])


def render_markdown(result: dict[str, Any], names: Sequence[str]) -> str:
    """bench.md: readable tables with the paper's numbers side by side."""
    parts = ["# pinnmpc benchmark", "", machine_line(result["machine"]), ""]
    if "step" in result:
        parts.append(md_step(result["step"], result["paper"], names))
    if "closed_loop" in result:
        parts.append(md_closed_loop(result["closed_loop"], result["paper"], names, result.get("optimality")))
        if result["closed_loop"].get("references"):
            parts.append(md_other_references(result["closed_loop"], names))
    if "optimality" in result:
        parts.append(md_optimality(result["optimality"]))
    if "scaling" in result:
        parts.append(md_scaling(result["scaling"]))
    if result.get("targets"):
        parts.append(md_targets(result["targets"]))
    elapsed = ", ".join(f"{k} {v:.1f} s" for k, v in result["elapsed_s"].items())
    parts += [f"Wall time per section: {elapsed}.", ""]
    return "\n".join(parts)


# ---------------------------------------------------------------------------------------------------------------
# Entry points


def run_bench(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Run the enabled sections; write bench.json, bench.md and plots into run_dir; return the JSON content."""
    run_dir = Path(run_dir)
    use_threads(cfg.threads)
    system: System = instantiate(cfg.system)
    names = tuple(system.state_names)
    pinn64 = load_surrogate(cfg.checkpoint, nx=len(names), nu=len(system.input_names))
    result: dict[str, Any] = {
        "machine": machine_info(),
        "paper": OmegaConf.to_container(cfg.paper, resolve=True),
        "config": OmegaConf.to_container(cfg, resolve=True),
    }
    elapsed: dict[str, float] = {}
    need_ref = cfg.closed_loop.enabled or cfg.optimality.enabled
    ref = (
        load_reference(resolve_reference_path(cfg.reference.path), pinn64.tau, cfg.reference.name) if need_ref else None
    )
    if cfg.step.enabled:
        t0 = time.perf_counter()
        pinn32 = load_surrogate(cfg.checkpoint, nx=len(names), nu=len(system.input_names), dtype=torch.float32)
        result["step"] = bench_step(cfg, system, pinn64, pinn32)
        elapsed["step"] = time.perf_counter() - t0
    problems: dict[str, list[OCPProblem]] = {}
    if cfg.closed_loop.enabled:
        t0 = time.perf_counter()
        result["closed_loop"], problems = bench_closed_loop(cfg, system, pinn64, ref)
        elapsed["closed_loop"] = time.perf_counter() - t0
    if cfg.optimality.enabled:
        t0 = time.perf_counter()
        result["optimality"] = {}
        for solver in optimality_solvers(cfg):
            if solver not in problems:  # no closed-loop row of this solver ran: record one
                _, problems[solver] = run_controller(cfg, system, pinn64, ref, solver, record=True)
            result["optimality"][solver] = bench_optimality(cfg, pinn64, solver, problems[solver])
            log.info("optimality: %s done", solver)
        elapsed["optimality"] = time.perf_counter() - t0
    if cfg.scaling.enabled:
        t0 = time.perf_counter()
        result["scaling"] = bench_scaling(cfg, system, pinn64, run_dir)
        elapsed["scaling"] = time.perf_counter() - t0
    result["targets"] = check_targets(cfg, result, names)
    result["elapsed_s"] = {k: float(v) for k, v in elapsed.items()}
    save_json(run_dir / "bench.json", result)
    markdown = render_markdown(result, names)
    atomic_write(run_dir / "bench.md", lambda p: p.write_text(markdown))
    return result


@hydra.main(version_base="1.3", config_path="../conf", config_name="bench")
def main(cfg: DictConfig) -> None:
    """CLI: run the benchmark and print its markdown."""
    run_dir = Path(hydra.core.hydra_config.HydraConfig.get().runtime.output_dir)
    run_cli(lambda: run_bench(cfg, run_dir), "pinnmpc.bench", run_dir)
    print((run_dir / "bench.md").read_text())
    print(f"outputs in {run_dir}")


if __name__ == "__main__":
    main()
