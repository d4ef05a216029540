"""Section 1: the cost of one step x_k -> x_k+1 of the PINN (torch float64/float32, numpy fast path) against
Euler, RK4 (numpy, torch, compiled C) and RK45 on the same rhs, with the one-step accuracy each one buys."""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig
from torch import Tensor

from pinnmpc.bench.common import integrator_h, make_plant, random_states
from pinnmpc.bench.timing import as_numpy, time_calls, timing_stats
from pinnmpc.plant.integrators import euler_step, rk4_step
from pinnmpc.plant.scipy_plant import ScipyPlant
from pinnmpc.surrogate.checkpoint import Surrogate
from pinnmpc.surrogate.flowmap import CompiledRK4
from pinnmpc.systems.base import System
from pinnmpc.training.data import reference_flow

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class StepMethod:
    """One way to compute x_k+1 from x_k; inputs are converted outside the timed call, so only the step is timed."""

    key: str
    label: str
    paper: str  # key into the paper's step_mean_s / step_median_s
    prepare: Callable[[np.ndarray, np.ndarray], tuple[Any, ...]]
    call: Callable[..., Any]
    vectorised: bool = True


def numpy_inputs(x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Contiguous float64 copies for the numpy integrators, the compiled step and the scipy plant."""
    return np.ascontiguousarray(x, dtype=np.float64), np.ascontiguousarray(u, dtype=np.float64)


def torch_inputs(dtype: torch.dtype) -> Callable[[np.ndarray, np.ndarray], tuple[Tensor, Tensor]]:
    """Converter to torch tensors of the given dtype."""

    def convert(x: np.ndarray, u: np.ndarray) -> tuple[Tensor, Tensor]:
        return torch.from_numpy(x).to(dtype).contiguous(), torch.from_numpy(u).to(dtype).contiguous()

    return convert


def _rk45_loop(plant: ScipyPlant, x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The plant has no batch: one solve_ivp per sample, as anyone using RK45 for a batch would have to."""
    return np.stack([plant.step(xi, ui) for xi, ui in zip(x, u)])


def compiled_rk4_method(system: System, tau: float, h: float) -> StepMethod | None:
    """RK4 of the true model generated as C by CasADi (None, with a warning, where nothing can compile it)."""
    try:
        compiled = CompiledRK4(system, tau, h)
    except RuntimeError as e:  # no C compiler, or the compile failed
        log.warning("step: no compiled RK4 row (%s)", e)
        return None
    return StepMethod("rk4_compiled", f"RK4 h={h:g} (compiled C, CasADi)", "rk4", numpy_inputs, compiled.step)


def step_methods(
    system: System, pinn64: Surrogate, pinn32: Surrogate, plant: ScipyPlant, h: float, compiled: bool = True
) -> list[StepMethod]:
    """Every row of the one-step table: the PINN in two precisions and as numpy, fixed-step baselines in numpy,
    torch and compiled C, and RK45."""
    tau = pinn64.tau
    pinn_numpy = pinn64.numpy_flow()  # what the Gauss-Newton controller evaluates
    euler = partial(euler_step, system.rhs, tau=tau, h=h)
    rk4 = partial(rk4_step, system.rhs, tau=tau, h=h)
    rk4_c = compiled_rk4_method(system, tau, h) if compiled else None
    return [
        StepMethod("pinn_f64", "PINN float64 (torch)", "pinn", torch_inputs(torch.float64), pinn64.step),
        StepMethod("pinn_f32", "PINN float32 (torch)", "pinn", torch_inputs(torch.float32), pinn32.step),
        StepMethod("pinn_numpy", "PINN float64 (numpy fast path)", "pinn", numpy_inputs, pinn_numpy.step),
        StepMethod("euler_numpy", f"Euler h={h:g} (numpy)", "euler", numpy_inputs, euler),
        StepMethod("euler_torch", f"Euler h={h:g} (torch)", "euler", torch_inputs(torch.float64), euler),
        StepMethod("rk4_numpy", f"RK4 h={h:g} (numpy)", "rk4", numpy_inputs, rk4),
        StepMethod("rk4_torch", f"RK4 h={h:g} (torch)", "rk4", torch_inputs(torch.float64), rk4),
        *([rk4_c] if rk4_c is not None else []),
        StepMethod(
            "rk45", "RK45 (scipy solve_ivp)", "rk45", numpy_inputs, partial(_rk45_loop, plant), vectorised=False
        ),
    ]


def time_method(method: StepMethod, x: np.ndarray, u: np.ndarray, batch: int, repeats: int, warmup: int) -> np.ndarray:
    """Timings at one batch size; batch 1 cycles through the states, since RK45's cost depends on the state."""
    if batch == 1:
        n = min(len(x), repeats + warmup)
        args = [method.prepare(x[i : i + 1], u[i : i + 1]) for i in range(n)]
        return time_calls(lambda i: method.call(*args[i % n]), repeats, warmup)
    batch_args = method.prepare(x[:batch], u[:batch])
    return time_calls(lambda _i: method.call(*batch_args), repeats, warmup)


def bench_step(cfg: DictConfig, system: System, pinn64: Surrogate, pinn32: Surrogate) -> dict[str, Any]:
    """The paper's Table 1 done right: median/mean/p95 per batch size, and the one-step RMSE each method buys."""
    sc = cfg.step
    if sc.rk45_batch not in ("loop", "skip"):
        raise ValueError(f"step.rk45_batch={sc.rk45_batch!r}; expected 'loop' or 'skip'")
    batches = [int(b) for b in sc.batch_sizes]
    h = integrator_h(pinn64.tau, sc.h)
    plant = make_plant(cfg, system, pinn64.tau)
    methods = step_methods(system, pinn64, pinn32, plant, h, bool(sc.compiled_rk4))
    x, u = random_states(system, max(int(sc.n_states), *batches), int(cfg.seed))
    xs, us = x[: int(sc.n_states)], u[: int(sc.n_states)]
    x_ref = reference_flow(system, torch.from_numpy(xs), torch.from_numpy(us), pinn64.tau, float(sc.ref_h)).numpy()
    motion = np.sqrt(np.mean((x_ref - xs) ** 2, axis=0))  # RMSE of x(tau) = x0: the yardstick for the rows above
    rmse: dict[str, dict[str, float]] = {}
    timing: dict[str, dict[str, dict[str, float]]] = {}
    rk45_median: dict[str, float] = {}
    with torch.no_grad():  # not inference_mode: a system may cache tensors its later autograd calls reuse
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
        "h_s": h,
        "ref_h_s": float(sc.ref_h),
        "n_states": int(sc.n_states),
        "repeats": int(sc.repeats),
        "warmup": int(sc.warmup),
        "rk45_batch": str(sc.rk45_batch),
        "rk45_loop_repeats": int(sc.rk45_loop_repeats),
        "methods": {m.key: {"label": m.label, "paper": m.paper} for m in methods},
        "rmse": rmse,
        "rmse_hold": {n: float(v) for n, v in zip(system.state_names, motion)},
        "timing": timing,
        "rk45_median_s": rk45_median,
    }
