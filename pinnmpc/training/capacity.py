"""Capacity check (`python -m pinnmpc.capacity`): can the configured network represent the one-step map at all?

The PINN learns x(tau) from the ODE residual (plus anchors) over hours. This check fits the same network
(model.*: widths, activation, gates, periodic inputs, angle sums) directly to true one-step results from fine RK4
at t = tau, by full-batch L-BFGS for a few minutes: plain regression of the one map the controller uses, the
easiest problem that network can be given. If its validation error stops falling above a state's one-step
target, more training of the PINN is unlikely to reach it: change the network (width, inputs) first. On planar3 a
short fit gets about where hours of PINN training ended (docs/training-findings.md).
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig
from torch import Tensor

from pinnmpc.surrogate.network import PINN
from pinnmpc.systems.base import System
from pinnmpc.systems.settings import job_system
from pinnmpc.training.data import random_pairs, reference_flow
from pinnmpc.training.job_settings import validate_capacity
from pinnmpc.util.io import save_json


def one_step_data(system: System, tau: float, n: int, h: float, seed: int) -> tuple[Tensor, Tensor, Tensor]:
    """n random (x0, u) over the training box and their true x(tau) (RK4 at step h), float64."""
    x0, u = random_pairs(system, n, seed)
    x0, u = x0.double(), u.double()
    return x0, u, reference_flow(system, x0, u, tau, h).double()


def _rmse(model: PINN, tau: float, x0: Tensor, u: Tensor, x1: Tensor) -> Tensor:
    """One-step RMSE per state, in state units."""
    dtype = model.out_scale.dtype
    with torch.no_grad():
        t = torch.full((len(x0), 1), tau, dtype=dtype)
        return (model(t, x0.to(dtype), u.to(dtype)).double() - x1).pow(2).mean(0).sqrt()


def fit_one_step(
    model: PINN,
    train: tuple[Tensor, Tensor, Tensor],
    val: tuple[Tensor, Tensor, Tensor],
    tau: float,
    minutes: float,
    max_steps: int | None,
    report: Any = None,
    lbfgs: tuple[int, int] = (50, 50),
    give_up_after: int = 3,
) -> dict[str, Any]:
    """Full-batch L-BFGS (lbfgs: iterations per call, history) on the squared error of x(tau) in output units, for
    `minutes` (or `max_steps` optimiser calls), stopping after `give_up_after` calls in a row without decrease; the
    history of the validation RMSE and the best state's errors."""
    from pinnmpc.training.module import lbfgs_evals, stalled  # the training's stall test; Lightning loads here

    dtype = model.out_scale.dtype
    x0, u, x1 = (a.to(dtype) for a in train)
    t = torch.full((len(x0), 1), tau, dtype=dtype)
    unit = model.out_scale
    optimiser = torch.optim.LBFGS(
        model.parameters(), lr=1.0, max_iter=lbfgs[0], history_size=lbfgs[1], line_search_fn="strong_wolfe",
        tolerance_grad=0.0, tolerance_change=0.0,
    )  # fmt: skip  # zero tolerances: the loss sits near 1e-6 in output units, below torch's absolute defaults

    def loss() -> Tensor:
        """The fitted loss: mean squared error of x(tau) in output units."""
        return ((model(t, x0, u) - x1) / unit).pow(2).mean()

    def closure() -> Tensor:
        optimiser.zero_grad()
        value = loss()
        value.backward()
        return value

    def score(rmse: Tensor) -> float:
        """The validation loss: squared errors in output units, as fitted."""
        return float((rmse / unit.double()).pow(2).sum())

    start, history, steps, resets, stuck = time.perf_counter(), [], 0, 0, 0
    initial = _rmse(model, tau, *val)
    best = score(initial)
    best_state = {k: v.clone() for k, v in model.state_dict().items()}
    while time.perf_counter() - start < 60.0 * minutes and (max_steps is None or steps < max_steps):
        evals = lbfgs_evals(optimiser)
        start_loss = float(optimiser.step(closure).detach())  # torch optimizers return the first closure value
        steps += 1
        with torch.no_grad():
            end_loss = float(loss())
        if not math.isfinite(end_loss):
            break  # a diverged step: keep the best state so far
        if stalled(start_loss, end_loss, lbfgs_evals(optimiser) - evals):
            # a line search that finds no decrease returns at once, and would again every call: forget the history
            optimiser.state.clear()
            resets, stuck = resets + 1, stuck + 1
            if stuck >= give_up_after:  # no decrease from a fresh history either: converged at this precision
                break
        else:
            stuck = 0
        rmse = _rmse(model, tau, *val)
        history.append({"seconds": time.perf_counter() - start, "val_rmse": rmse.tolist()})
        if score(rmse) < best:  # keep the best validation state, as training keeps its best checkpoint
            best, best_state = score(rmse), {k: v.clone() for k, v in model.state_dict().items()}
        if report is not None:
            report(steps, history[-1])
    model.load_state_dict(best_state)
    return {
        "initial_val_rmse": initial.tolist(),
        "val_rmse": _rmse(model, tau, *val).tolist(),
        "train_rmse": _rmse(model, tau, *train).tolist(),
        "steps": steps,
        "resets": resets,
        "stopped": "no decrease" if stuck >= give_up_after else "budget",
        "seconds": time.perf_counter() - start,
        "history": history,
    }


def run_capacity(
    cfg: DictConfig,
    run_dir: Path,
    command: str = "python -m pinnmpc.capacity",
    say: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """capacity.json, capacity.png and surrogate.pt: the network's one-step error after a direct fit, against the
    targets, and the fitted network (`command` goes into its provenance; `say` prints the progress lines)."""
    from pinnmpc.training.models import fresh_model  # Lightning loads only when the check runs

    system = job_system(cfg, validate_capacity)
    torch.manual_seed(int(cfg.seed))
    model = fresh_model(cfg, system).to(getattr(torch, cfg.dtype))
    tau, h = float(system.tau), float(cfg.h)
    train = one_step_data(system, tau, int(cfg.points), h, int(cfg.seed))
    val = one_step_data(system, tau, int(cfg.val_points), h, int(cfg.seed) + 1)
    every = max(1.0, 60.0 * float(cfg.minutes) / 10)  # about ten progress lines per run
    last = [0.0]

    def report(step: int, entry: dict[str, Any]) -> None:
        if say is not None and cfg.progress and entry["seconds"] - last[0] >= every:
            last[0] = entry["seconds"]
            worst = ", ".join(f"{n} {v:.2e}" for n, v in zip(system.state_names, entry["val_rmse"]))
            say(f"{entry['seconds']:5.0f} s, step {step}: validation RMSE {worst}")

    lbfgs = (int(cfg.lbfgs.max_iter), int(cfg.lbfgs.history))
    fit = fit_one_step(model, train, val, tau, float(cfg.minutes), cfg.max_steps, report, lbfgs, int(cfg.give_up_after))
    targets = cfg.system.get("targets", {}).get("one_step_rmse")
    result = {
        "system": system.name,
        "state_names": list(system.state_names),
        "model": {k: model.config[k] for k in ("hidden", "activation", "ic", "time_basis", "periodic", "angle_sums")},
        "parameters": sum(p.numel() for p in model.parameters()),
        "points": int(cfg.points),
        "val_points": int(cfg.val_points),
        "targets": None if targets is None else list(targets),
        "dtype": str(cfg.dtype),
        **fit,
    }
    save_json(run_dir / "capacity.json", result)
    _save_network(model, system, tau, {**result, "trained_with": command}, run_dir)
    if cfg.plots:
        _draw(result, run_dir)
    return result


def _save_network(model: PINN, system: System, tau: float, result: dict[str, Any], run_dir: Path) -> None:
    """surrogate.pt: the fitted network, for a closed loop (it is right at t = tau only, all the controller uses) or
    as init_from of a training."""
    from pinnmpc.surrogate.checkpoint import Surrogate  # it converts the network it is given: a copy

    meta = {
        "trained_with": result["trained_with"],
        "kind": "direct fit of x(tau) to fine RK4, no physics loss: x(t) for t != tau is untrained",
        "training_time_s": result["seconds"],
        "val_rmse": result["val_rmse"],
    }
    names = tuple(system.state_names), tuple(system.input_names)
    Surrogate(copy.deepcopy(model), tau, *names, meta).save(run_dir / "surrogate.pt")


def _draw(result: dict[str, Any], run_dir: Path) -> None:
    """capacity.png: validation and training RMSE per state against the targets."""
    from pinnmpc.util.plots import basis_figure, save_figure

    m = result["model"]
    title = (
        f"{result['system']}: {m['hidden']} {m['activation']} fitted to {result['points']} true steps "
        f"for {result['seconds'] / 60:.1f} min"
    )
    fig = basis_figure(
        [result["val_rmse"], result["train_rmse"]], ["validation", "training"], result["state_names"],
        result["targets"], title, ylabel="one-step RMSE at tau (state units)", legend="direct fit",
    )  # fmt: skip
    save_figure(fig, run_dir / "capacity.png")
