"""Faults a closed loop survives: wrappers around the measurement (a bad sample, a delayed sample) and the plant (a
payload change, lost input authority), the guard that screens every measurement before the controller sees it, and
how fast tracking recovered after each fault."""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from pinnmpc.plant.base import Plant

Predict = Callable[[np.ndarray, np.ndarray], np.ndarray]  # the controller model's one step F(x, u)


@dataclass
class Reading:
    """One measurement as the loop receives it: the state and how many samples old it is (its time stamp)."""

    value: np.ndarray
    age: int = 0


class Sensor(Protocol):
    """The measurement chain: the true state in, what the loop receives out, one call per sample."""

    def read(self, k: int, x: np.ndarray) -> Reading:
        """The reading of sample k taken from the true state x."""
        ...

    def faults(self) -> list[dict[str, Any]]:
        """The faults this chain injected (empty: none)."""
        ...


@dataclass
class NoisySensor:
    """The plain sensor: Gaussian noise of std sigma on every state (one draw per sample, even at sigma 0, so that a
    seed gives one noise sequence whatever else is configured)."""

    sigma: float
    rng: np.random.Generator

    def read(self, k: int, x: np.ndarray) -> Reading:
        """x plus noise."""
        return Reading(x + self.sigma * self.rng.standard_normal(x.shape[0]))

    def faults(self) -> list[dict[str, Any]]:
        """None: noise is no fault."""
        return []


@dataclass
class BadSample:
    """One sample of one state replaced by NaN or shifted by an outlier (a sensor glitch)."""

    inner: Sensor
    step: int
    state: int
    kind: str  # "nan" | "outlier"
    jump: float  # outlier size, in the state's unit
    label: str  # the state's name, for the report

    def read(self, k: int, x: np.ndarray) -> Reading:
        """The inner reading, hit at the fault's step."""
        r = self.inner.read(k, x)
        if k == self.step:
            value = r.value.copy()
            value[self.state] = np.nan if self.kind == "nan" else value[self.state] + self.jump
            r = Reading(value, r.age)
        return r

    def faults(self) -> list[dict[str, Any]]:
        """This glitch, then the inner chain's."""
        what = "NaN" if self.kind == "nan" else f"outlier of {self.jump:+.3g}"
        own = {"fault": "measurement", "what": f"{what} on {self.label}", "onset_step": self.step}
        return [{**own, "end_step": self.step + 1}, *self.inner.faults()]


@dataclass
class DelayedSensor:
    """Within [start, end) the loop receives the previous sample's reading, stamped one sample old."""

    inner: Sensor
    start: int
    end: int
    _previous: Reading | None = None

    def read(self, k: int, x: np.ndarray) -> Reading:
        """The previous reading inside the window (the inner chain is read every sample all the same)."""
        fresh = self.inner.read(k, x)
        previous, self._previous = self._previous, fresh
        if self.start <= k < self.end and previous is not None:
            return Reading(previous.value, previous.age + 1)
        return fresh

    def faults(self) -> list[dict[str, Any]]:
        """This delay, then the inner chain's."""
        own = {"fault": "delay", "what": "measurement one sample late", "onset_step": self.start}
        return [{**own, "end_step": self.end}, *self.inner.faults()]


class _PlantWrapper:
    """What every plant wrapper passes through: tau, timings, stick-slip count; it counts the steps it was given."""

    inner: Plant
    k: int

    @property
    def tau(self) -> float:
        """The wrapped plant's control period."""
        return self.inner.tau

    @property
    def step_times(self) -> list[float]:
        """The wrapped plant's step timings."""
        return self.inner.step_times

    @property
    def stick_slip_steps(self) -> int:
        """The wrapped plant's stick-slip redos."""
        return self.inner.stick_slip_steps

    @property
    def delay_periods(self) -> int:
        """The wrapped plant's: periods it holds each input late."""
        return int(getattr(self.inner, "delay_periods", 0))

    def faults(self) -> list[dict[str, Any]]:
        """The inner plant's faults, if it is a wrapper too."""
        inner = getattr(self.inner, "faults", None)
        return inner() if inner is not None else []


class AuthorityLoss(_PlantWrapper):
    """Within [start, end) the plant receives gain * u_j on input j (a weak motor or amplifier)."""

    def __init__(self, inner: Plant, joint: int, gain: float, start: int, end: int, label: str) -> None:
        self.inner, self.joint, self.gain, self.label, self.k = inner, joint, gain, label, 0
        self.start, self.end = start, end

    def step(self, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
        """One period with the input scaled inside the window."""
        k, self.k = self.k, self.k + 1
        if self.start <= k < self.end:
            u = np.array(u, dtype=np.float64)
            u[self.joint] *= self.gain
        return self.inner.step(x0, u)

    def faults(self) -> list[dict[str, Any]]:
        """This loss of authority, then the inner plant's."""
        own = {"fault": "authority", "what": f"input {self.label} x {self.gain:g} at the plant"}
        return [{**own, "onset_step": self.start, "end_step": self.end}, *super().faults()]


class PlantSwitch(_PlantWrapper):
    """From step `at` on, a second plant (the same arm with another payload or mass) continues from the same state."""

    def __init__(self, inner: Plant, second: Plant, at: int, what: str) -> None:
        self.inner, self.second, self.at, self.what, self.k = inner, second, at, what, 0

    def step(self, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
        """One period on the plant of the moment."""
        k, self.k = self.k, self.k + 1
        return (self.inner if k < self.at else self.second).step(x0, u)

    @property
    def step_times(self) -> list[float]:
        """Both plants' step timings, in order."""
        return [*self.inner.step_times, *self.second.step_times]

    @property
    def stick_slip_steps(self) -> int:
        """Both plants' stick-slip redos."""
        return self.inner.stick_slip_steps + self.second.stick_slip_steps

    def faults(self) -> list[dict[str, Any]]:
        """This change (for good; its first step is what recovery counts from), then the inner plant's."""
        own = {"fault": "payload", "what": self.what, "onset_step": self.at, "end_step": self.at + 1}
        return [own, *super().faults()]


@dataclass
class MeasurementGuard:
    """Screens each reading before the controller sees it: a non-finite reading, or one whose innovation (the jump
    from the model's prediction plus the controller's disturbance estimate) exceeds max(sigmas x the recent
    innovations' robust std, floor) in any state, is rejected and that prediction (no model: the last good
    measurement) used instead; after max_rejects rejections in a row a jump is accepted (the robot changed, not the
    sensor). A stale reading is predicted forward by the model with the inputs applied since."""

    predict: Predict | None
    sigmas: float = 6.0
    floor: float = 0.1  # positions (the first half of the state), rad
    velocity_floor: float = 1.0  # velocities (the second half), rad/s
    window: int = 30
    warmup: int = 10
    max_rejects: int = 2
    counts: dict[str, int] = field(default_factory=dict)
    _residuals: deque[np.ndarray] = field(default_factory=lambda: deque(maxlen=30))
    _inputs: deque[np.ndarray] = field(default_factory=lambda: deque(maxlen=8))
    _in_a_row: int = 0
    events: list[tuple[int, str]] = field(default_factory=list)  # (step, action) of every intervention

    def __post_init__(self) -> None:
        self._residuals = deque(maxlen=max(int(self.window), 1))
        for key in ("rejected_nonfinite", "rejected_jump", "accepted_jump", "stale_compensated", "inputs_held"):
            self.counts.setdefault(key, 0)

    def applied(self, u: np.ndarray) -> None:
        """Note the input the plant got (stale readings are predicted forward with these)."""
        self._inputs.append(np.asarray(u, dtype=np.float64))

    def limit(self) -> np.ndarray | None:
        """The per-state jump limit now (None: too few residuals yet, only non-finite readings are rejected)."""
        if len(self._residuals) < self.warmup:
            return None
        r = np.array(self._residuals)
        spread = 1.4826 * np.median(np.abs(r - np.median(r, axis=0)), axis=0)
        half = r.shape[1] // 2
        floor = np.where(np.arange(r.shape[1]) < half, self.floor, self.velocity_floor)
        return np.maximum(self.sigmas * spread, floor)

    def screen(
        self,
        k: int,
        reading: Reading,
        predicted: np.ndarray | None,
        last_good: np.ndarray,
        offset: np.ndarray | None = None,
    ) -> np.ndarray:
        """The measurement the controller gets at sample k (predicted: the model's F(previous, u), None: none;
        offset: the controller's disturbance estimate, added to what stands in for a rejected reading)."""
        value = reading.value
        if reading.age > 0 and np.all(np.isfinite(value)):
            return self._stale(k, value, reading.age, offset)
        expected = None
        if predicted is not None and np.all(np.isfinite(predicted)):
            expected = predicted if offset is None or not np.all(np.isfinite(offset)) else predicted + offset
        substitute = last_good if expected is None else expected
        if not np.all(np.isfinite(value)):
            return self._reject(k, "rejected_nonfinite", substitute)
        if expected is None:
            return value
        residual = value - expected
        limit = self.limit()
        if limit is not None and np.any(np.abs(residual) > limit):
            if self._in_a_row < self.max_rejects:
                return self._reject(k, "rejected_jump", substitute)
            self.counts["accepted_jump"] += 1
            self.events.append((k, "accepted_jump"))
            self._residuals.clear()  # the robot changed: learn its residuals afresh
        self._in_a_row = 0
        self._residuals.append(residual)
        return value

    def _reject(self, k: int, why: str, substitute: np.ndarray) -> np.ndarray:
        """Count a rejection and hand back the substitute."""
        self.counts[why] += 1
        self.events.append((k, why))
        self._in_a_row += 1
        return substitute.copy()

    def _stale(self, k: int, value: np.ndarray, age: int, offset: np.ndarray | None) -> np.ndarray:
        """A reading `age` samples old, brought to now by the model with the inputs applied since (no model: as is)."""
        self.counts["stale_compensated"] += 1
        self.events.append((k, "stale_compensated"))
        if self.predict is None or len(self._inputs) < age:
            return value
        x = value
        for u in list(self._inputs)[-age:]:
            x = self.predict(x, u)
            if offset is not None and np.all(np.isfinite(offset)):
                x = x + offset
        return x

    def safe_input(self, k: int, u: np.ndarray, previous: np.ndarray | None) -> np.ndarray:
        """A non-finite controller output never reaches the plant: the previous input (zeros at first) is held."""
        if np.all(np.isfinite(u)):
            return u
        self.counts["inputs_held"] += 1
        self.events.append((k, "inputs_held"))
        return np.zeros_like(u) if previous is None else previous.copy()

    def report(self) -> dict[str, Any]:
        """What the guard did, and its thresholds."""
        limits = {"sigmas": self.sigmas, "floor": self.floor, "velocity_floor": self.velocity_floor}
        return {**self.counts, **limits, "max_rejects": self.max_rejects}


ACTIONS = {  # what was done, in words, per guard count
    "rejected_nonfinite": "rejected (non-finite)",
    "rejected_jump": "rejected (jump beyond the limit)",
    "accepted_jump": "accepted after {max_rejects} rejections (the robot changed)",
    "stale_compensated": "predicted forward by the model (stale)",
    "inputs_held": "previous input held (non-finite controller output)",
}


def position_error(x: np.ndarray, x_ref: np.ndarray, nq: int) -> np.ndarray:
    """The worst joint-angle error per sample: what recovery is measured on."""
    return np.abs(x[:, :nq] - x_ref[: len(x), :nq]).max(axis=1)


def recovery(error: np.ndarray, onset: int, end: int, window: int, factor: float, tolerance: float) -> dict[str, Any]:
    """Samples from a fault's end (state index `end`: the last state the fault's steps drove, or the first one a
    one-step fault hit) until the worst joint-angle error is back at or below its pre-fault level: factor x its worst
    over the `window` samples up to the onset, or `tolerance` where that is higher (None: not within the run)."""
    before = error[max(onset - window + 1, 0) : onset + 1]
    if onset < 1 or end >= len(error):
        return {"error_before": None, "error_peak": None, "recovery_level": None, "recovery_samples": None}
    level = max(factor * float(before.max()), tolerance)
    below = np.flatnonzero(error[end:] <= level)
    samples = int(below[0]) if below.size else None
    stop = len(error) if samples is None else end + samples + 1
    return {
        "error_before": float(before.max()),  # rad
        "error_peak": float(error[onset + 1 : stop].max(initial=0.0)),  # rad, from the first state it could touch
        "recovery_level": level,  # rad
        "recovery_samples": samples,
    }


def fault_report(
    events: list[dict[str, Any]],
    guard: MeasurementGuard,
    error: np.ndarray,
    tau: float,
    window: int,
    factor: float,
    tolerance: float,
    bound: int,
) -> list[dict[str, Any]]:
    """Each injected fault with what the guard did during it and how many samples tracking took to recover."""
    out = []
    for ev in sorted(events, key=lambda e: e["onset_step"]):
        onset, end = ev["onset_step"], ev["end_step"]
        if onset >= len(error) - 1:  # the run ended before the fault's step
            out.append({**ev, "t": onset * tau, "actions": ["not reached: the run ended first"], "recovered": None})
            continue
        done = {a for k, a in guard.events if onset <= k < max(end, onset + 1)}
        actions = [ACTIONS[a].format(max_rejects=guard.max_rejects) for a in ACTIONS if a in done]
        rec = recovery(error, onset, end, window, factor, tolerance)
        n = rec["recovery_samples"]
        out.append(
            {
                **ev,
                "t": onset * tau,
                "actions": actions or ["none needed (the controller absorbed it)"],
                **rec,
                "recovered": n is not None and n <= bound,
                "recovery_bound": bound,
            }
        )
    return out
