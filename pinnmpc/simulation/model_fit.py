"""Does the controller's model fit the robot? The model monitor's one-step miss against the model's own level."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from pinnmpc.controller.base import Controller
from pinnmpc.plant.integrators import rk4_step
from pinnmpc.systems.base import System

# The verdict compares medians: a closed loop's p95 on the model itself sits up to about 5x the network's one-step
# RMSE (the references visit where the network misses most), its median within 1.3x (the three arms' shipped
# networks on their built-in references).
FIT_RATIO = 4.0  # a median one-step miss past this multiple of the model's own level: the model does not fit
NOISE_MEDIAN = 1.0  # median of |n(k+1) - n(k)| for Gaussian measurement noise of noise_sigma, in sigmas (0.95)
LEVEL_FLOOR = 1e-5  # rad: the smallest level counted (a true model's level is the plant's integration error)
LEVEL_POINTS = 256  # random (x0, u) the level is measured on where the checkpoint does not record it
LEVEL_H = 5e-4  # s: the RK4 step of the true steps it is measured against
LEVEL_SEED = 0  # the level's points are the same in every run


def recorded_level(controller: Controller) -> float | None:
    """The network's one-step level as training recorded it (best_val_rmse_position: its worst joint angle's RMSE at
    tau on the validation steps), where the controller predicts with that network; None where it does not."""
    if controller.describe().get("prediction", "surrogate") != "surrogate":
        return None  # the true model's values or the prior alone: not what the checkpoint measured
    meta = getattr(getattr(controller, "surrogate", None), "meta", None) or {}
    value = meta.get("best_val_rmse_position")
    if isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value) and value > 0:
        return float(value)
    return None


def measured_level(controller: Controller, system: System, points: int = LEVEL_POINTS) -> float:
    """The controller model's one-step RMSE on the model itself, the worst joint angle's, over random states and
    inputs of the training box: the level of a network whose checkpoint does not record one (a training .ckpt)."""
    rng = np.random.default_rng(LEVEL_SEED)
    box, ubox = system.state_box, system.input_box
    x0 = rng.uniform(box.low, box.high, (points, len(box.low)))
    u = rng.uniform(ubox.low, ubox.high, (points, len(ubox.low)))
    tau = float(controller_tau(controller, system))
    with torch.no_grad():
        true = rk4_step(system.fast_rhs, torch.from_numpy(x0), torch.from_numpy(u), tau, LEVEL_H).numpy()
    zero = np.zeros(x0.shape[1])
    predicted = np.stack([-controller.prediction_error(x, v, zero) for x, v in zip(x0, u)])  # type: ignore[attr-defined]
    rmse = np.sqrt(np.mean((predicted - true) ** 2, axis=0))
    return float(rmse[: system.nq].max())


def controller_tau(controller: Controller, system: System) -> float:
    """The period the controller's model predicts over (its network's tau; the system's for any other model)."""
    surrogate = getattr(controller, "surrogate", None)
    return float(getattr(surrogate, "tau", system.tau))


def model_fit(
    monitor: dict[str, Any] | None, controller: Controller, system: System, noise_sigma: float = 0.0
) -> dict[str, Any]:
    """metrics.json's verdict on the model monitor, so a model that does not fit the robot is said, not inferred:
    `model_fits` (None without a model step) and `model_miss_ratio`, the worst joint angle's median one-step miss
    over the model's own level (plus what the measurement noise alone adds); the level and its source go into the
    monitor's record."""
    if not monitor or not getattr(controller, "prediction_error", None):
        return {"model_fits": None, "model_miss_ratio": None}
    level, source = recorded_level(controller), "checkpoint"
    if level is None:
        level, source = measured_level(controller, system), "measured on the model"
    names = list(monitor["median"])[: system.nq]
    worst = max(names, key=lambda n: monitor["median"][n])
    expected = max(level, LEVEL_FLOOR) + NOISE_MEDIAN * max(float(noise_sigma), 0.0)
    ratio = float(monitor["median"][worst] / expected)
    monitor.update({"level": level, "level_source": source, "expected": expected, "worst": worst})
    return {"model_fits": bool(ratio <= FIT_RATIO), "model_miss_ratio": ratio}


def fit_note(m: dict[str, Any]) -> str:
    """The headline's word on a model that does not fit the robot, and what to do about it (nothing when it fits)."""
    mon = m.get("model_monitor") or {}
    if m.get("model_fits") is not False or "worst" not in mon:
        return ""
    worst = mon["worst"]
    unit = (m.get("state_units") or {}).get(worst, "")
    miss = f"{mon['median'][worst]:.1e} {unit}".rstrip()
    level = f"{mon['expected']:.1e} {unit}".rstrip()
    return (
        f"; the model does not fit the robot: its one-step miss is {m['model_miss_ratio']:.0f}x its own level "
        f"(median {miss} on {worst} against {level}): log the robot and fine-tune the network on the logs, or "
        "identify the model (docs/robot.md)"
    )
