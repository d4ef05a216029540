"""Section 3: how far each solver's solutions lie from the best of several tight scipy L-BFGS-B solves of the very
OCPs its closed loop solved, on the same surrogate."""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig
from scipy.optimize import minimize

from pinnmpc.bench.common import controller_cfg
from pinnmpc.bench.loops import OCPProblem
from pinnmpc.bench.timing import PERCENTILE
from pinnmpc.controller.build import build_nmpc
from pinnmpc.controller.ocp import HorizonOCP
from pinnmpc.surrogate.checkpoint import Surrogate


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
        "real_time": bool(getattr(nmpc.solver, "rti", False)),  # one step per sample: near the optimum, not at it
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
