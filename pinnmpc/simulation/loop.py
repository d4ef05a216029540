"""The receding-horizon loop itself: controller, plant and reference in, the trajectory out (no config, no files)."""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from tqdm.auto import tqdm

from pinnmpc.controller.base import Controller
from pinnmpc.plant.base import Plant, PlantError
from pinnmpc.references.data import Reference
from pinnmpc.simulation.faults import MeasurementGuard, NoisySensor, Predict, Sensor
from pinnmpc.systems.base import Box, System

log = logging.getLogger(__name__)


@dataclass
class LoopResult:
    """What one closed loop reached: states (steps + 1, nx), the inputs applied (steps, nu) and how it ended."""

    x: np.ndarray
    u: np.ndarray
    status: str  # "ok", "interrupted", "plant_failure: ..." or "failed: ..."
    out_of_box_steps: int  # measured states outside the model's training box
    prediction_error: np.ndarray | None = None  # (steps - 1, nx): measured next state less the controller model's
    #   one-step prediction from the measured state and the applied input (the model monitor; None: no model)
    faults: list[dict[str, Any]] = field(default_factory=list)  # what the sensor chain and plant wrappers injected
    guard: MeasurementGuard | None = None  # what screened the measurements (its counts and events)


def run_loop(
    controller: Controller,
    plant: Plant,
    ref: Reference,
    *,
    x0: Sequence[float] | None = None,
    max_steps: int | None = None,
    domain: Box | None = None,
    state_box: Box | None = None,
    noise_sigma: float = 0.0,
    seed: int = 0,
    progress: bool = True,
    stop: Callable[[], bool] | None = None,
    sensor: Sensor | None = None,
    guard: MeasurementGuard | None = None,
) -> LoopResult:
    """Receding-horizon loop from x0 (None: the reference's first sample); stops cleanly on a plant failure, when the
    state leaves state_box by more than its width (a diverged simulation or controller) or when stop() turns true
    (a signal), and returns what was reached. sensor (default: Gaussian noise of noise_sigma, seeded) gives each
    measurement, guard (default: MeasurementGuard on the controller's model) screens it before the controller
    sees it, and no non-finite input ever reaches the plant."""
    horizon, nx = controller.horizon, ref.x.shape[1]
    delay = delay_compensation(controller, plant)
    steps = len(ref) - horizon - 1 - delay
    if steps < 1:
        raise ValueError(
            f"reference {ref.name} has {len(ref)} samples at tau; horizon {horizon} needs at least "
            f"{horizon + 2 + delay}"
        )
    if max_steps is not None:
        steps = min(steps, int(max_steps))
    sensor = NoisySensor(noise_sigma, np.random.default_rng(seed)) if sensor is None else sensor
    lo = np.full(nx, -np.inf) if domain is None else np.array(domain.low)
    hi = np.full(nx, np.inf) if domain is None else np.array(domain.high)
    controller.reset()
    x = np.array(ref.x[0] if x0 is None else x0, dtype=np.float64)
    xs, us, status, out_of_box_steps, warned = [x], [], "ok", 0, False
    monitor = getattr(controller, "prediction_error", None)  # the controller's model, one step (None: it has none)
    predict = None if monitor is None else model_step(monitor, nx)
    guard = MeasurementGuard(predict) if guard is None else guard
    errors, last, u_applied = [], None, None
    low, high = (np.asarray(b, dtype=np.float64) for b in (controller.low, controller.high))
    running = np.clip(np.zeros(len(low)), low, high)  # the input a late plant holds over the coming period
    for k in tqdm(range(steps), desc="closed loop", unit="step", disable=not progress, file=sys.stderr):
        if stop is not None and stop():
            status = "interrupted"
            log.warning("interrupted after %d of %d steps; writing what was reached", k, steps)
            break
        reading = sensor.read(k, x)
        predicted = None if predict is None or last is None else predict(*last)
        offset = getattr(controller, "disturbance", None)  # the offset-free estimate: what the model misses
        measured = guard.screen(k, reading, predicted, reading.value if last is None else last[0], offset)
        if np.any(measured < lo) or np.any(measured > hi):
            out_of_box_steps += 1
            if not warned:
                log.warning(
                    "state %s at step %d is outside the surrogate's training box; predictions may be poor",
                    measured.round(3).tolist(),
                    k,
                )
                warned = True
        if predicted is not None and measured is reading.value:  # a fresh reading the guard accepted
            errors.append(measured - predicted)
        window = ref.x[k + 1 + delay : k + 1 + delay + horizon]  # a late plant: the plan starts a period on
        u = guard.safe_input(k, np.asarray(controller.make_step(measured, window)), u_applied)
        u_applied = np.asarray(u, dtype=np.float64)
        guard.applied(u_applied)
        try:
            x = plant.step(x, u)
        except PlantError as e:
            status = f"plant_failure: {e}"
            log.error("%s; stopping after %d steps", status, k)
            us.append(u)
            break
        u = sent_instead(controller, plant, u)
        last, running = (measured, running if delay else u), u  # what drove the plant over the period, and next
        xs.append(x)
        us.append(u)
        far = diverged(x, state_box)
        if far:
            status = f"failed: {far} after step {k}: the simulation or the controller diverged"
            log.error("%s; stopping", status)
            break
    U = np.array(us, dtype=np.float64).reshape(-1, len(controller.low))
    E = None if monitor is None else np.array(errors, dtype=np.float64).reshape(-1, nx)
    injected = [*sensor.faults(), *(plant.faults() if hasattr(plant, "faults") else [])]
    return LoopResult(np.array(xs), U, status, out_of_box_steps, E, injected, guard)


def sent_instead(controller: Controller, plant: Plant, u: np.ndarray) -> np.ndarray:
    """The input the plant sent for u (a robot's safety layer clips and slows commands), told to a controller that
    predicts with it; u where the plant does not say."""
    sent = getattr(plant, "last_command", None)
    if sent is None or np.array_equal(sent, u):
        return u
    if hasattr(controller, "applied_input"):
        controller.applied_input(sent)
    return np.array(sent, dtype=np.float64)


def delay_compensation(controller: Controller, plant: Plant) -> int:
    """Periods a plant holds each input late (plant.command_at = tau: 1), handed to the controller, which then plans
    from its prediction of the state the input will meet; a controller without that ability is refused."""
    delay = int(getattr(plant, "delay_periods", 0))
    if delay and not hasattr(controller, "delay_periods"):
        raise ValueError(
            f"the plant sends each command a period late (plant.command_at = tau) and {type(controller).__name__} "
            "cannot plan ahead of it; expected plant.command_at < tau or a controller with a model"
        )
    if hasattr(controller, "delay_periods"):
        controller.delay_periods = delay
    return delay


def model_step(monitor: Callable[..., np.ndarray], nx: int) -> Predict:
    """The controller model's one step F(x, u) from its monitor's x - F(x_prev, u_prev) (exactly: 0 - F, negated)."""
    zero = np.zeros(nx)
    return lambda x, u: -monitor(x, u, zero)


def divergence_box(system: System) -> Box:
    """The state box, with unbounded positions on arms whose joints turn all the way round (no joint limits)."""
    low, high = np.array(system.state_box.low, dtype=float), np.array(system.state_box.high, dtype=float)
    if system.joint_limits is None:
        low[: system.nq], high[: system.nq] = -np.inf, np.inf
    return Box(low.tolist(), high.tolist())


def diverged(x: np.ndarray, box: Box | None) -> str:
    """What is wrong with a state that is not finite or lies beyond box by more than the box's width ('' if none)."""
    if not np.all(np.isfinite(x)):
        return f"the state became non-finite ({x.tolist()})"
    if box is None:
        return ""
    beyond = np.flatnonzero(far_outside(x, box))
    if not beyond.size:
        return ""
    j, low, high = int(beyond[0]), box.low, box.high
    return f"state {j} = {x[j]:.3g}, beyond the state box [{low[j]:.3g}, {high[j]:.3g}] by more than its width"


def far_outside(x: np.ndarray, box: Box) -> np.ndarray:
    """Which entries of states x (..., n) lie beyond the box by more than its width: no arm of the system goes there."""
    low, high = np.asarray(box.low, dtype=float), np.asarray(box.high, dtype=float)
    return (x < low - (high - low)) | (x > high + (high - low))
