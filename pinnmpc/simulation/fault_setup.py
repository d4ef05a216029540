"""The `faults:` settings (conf/closed_loop.yaml, conf/bench.yaml) checked and turned into the loop's sensor chain,
plant wrappers, measurement guard and recovery yardstick; nothing configured leaves the loop as it was."""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf

from pinnmpc.plant.base import Plant
from pinnmpc.simulation.faults import (
    AuthorityLoss,
    BadSample,
    DelayedSensor,
    MeasurementGuard,
    NoisySensor,
    PlantSwitch,
    Predict,
    Sensor,
)
from pinnmpc.systems.base import System

GUARD_DEFAULTS = {  # faults.guard in conf/closed_loop.yaml
    "sigmas": 6.0,
    "floor": 0.1,
    "velocity_floor": 1.0,
    "window": 30,
    "warmup": 10,
    "max_rejects": 2,
}
RECOVERY_DEFAULTS = {"window": 10, "factor": 2.0, "tolerance": 1e-3, "samples": 20}  # faults.recovery


@dataclass(frozen=True)
class Recovery:
    """How recovery is judged: the worst error over `window` samples before a fault, times `factor` (at least
    `tolerance`), must be reached again within `samples` samples after it."""

    window: int = 10
    factor: float = 2.0
    tolerance: float = 1e-3
    samples: int = 20


@dataclass
class FaultPlan:
    """What the loop runs with: the (wrapped) plant, the sensor chain, the guard and the recovery yardstick."""

    plant: Plant
    sensor: Sensor
    guard: MeasurementGuard
    recovery: Recovery


def _plain(node: Any) -> dict[str, Any]:
    """A settings node as a dict (None: empty)."""
    if node is None:
        return {}
    if isinstance(node, DictConfig):
        return OmegaConf.to_container(node, resolve=True)  # type: ignore[return-value]
    return dict(node)


def _number(key: str, value: Any, what: str, low: float = -math.inf, integer: bool = False) -> float:
    """A finite number (an integer where asked) at or above low, else a one-line error naming the key."""
    ok = not isinstance(value, bool) and isinstance(value, int | float) and math.isfinite(value) and value >= low
    if ok and integer and float(value) != int(value):
        ok = False
    if not ok:
        raise ValueError(f"faults.{key}={value!r}; expected {what}")
    return int(value) if integer else float(value)


def _step(key: str, t: Any, tau: float) -> int:
    """A fault time in seconds as the sample it falls on."""
    return int(round(_number(key, t, "a time >= 0 in seconds", 0.0) / tau))


def _index(key: str, value: Any, names: tuple[str, ...]) -> int:
    """A state or input index, or its name."""
    if isinstance(value, str) and value in names:
        return names.index(value)
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < len(names):
        raise ValueError(f"faults.{key}={value!r}; expected an index 0..{len(names) - 1} or one of {list(names)}")
    return value


def check_keys(where: str, given: Mapping[str, Any], known: tuple[str, ...]) -> None:
    """A misspelt fault setting is an error, not silently off."""
    unknown = sorted(set(given) - set(known))
    if unknown:
        raise ValueError(f"faults.{where} has unknown keys {unknown}; expected some of {list(known)}")


def build_guard(cfg: Mapping[str, Any], predict: Predict | None) -> MeasurementGuard:
    """The measurement guard from faults.guard (defaults where a key is absent)."""
    check_keys("guard", cfg, tuple(GUARD_DEFAULTS))
    g = {**GUARD_DEFAULTS, **{k: v for k, v in cfg.items() if v is not None}}
    return MeasurementGuard(
        predict,
        sigmas=_number("guard.sigmas", g["sigmas"], "a number > 0", 1e-12),
        floor=_number("guard.floor", g["floor"], "a number >= 0 (rad)", 0.0),
        velocity_floor=_number("guard.velocity_floor", g["velocity_floor"], "a number >= 0 (rad/s)", 0.0),
        window=_number("guard.window", g["window"], "an integer >= 2", 2, integer=True),  # type: ignore[arg-type]
        warmup=_number("guard.warmup", g["warmup"], "an integer >= 2", 2, integer=True),  # type: ignore[arg-type]
        max_rejects=_number("guard.max_rejects", g["max_rejects"], "an integer >= 0", 0, integer=True),  # type: ignore[arg-type]
    )


def plan_faults(
    cfg: Any,
    system: System,
    plant: Plant,
    *,
    plant_cfg: Any,
    robots: Any,
    noise_sigma: float,
    seed: int,
    predict: Predict | None,
) -> FaultPlan:
    """The loop's sensor chain, plant and guard from the `faults:` settings (None or all off: the plain loop)."""
    f = _plain(cfg)
    check_keys("", f, ("measurement", "payload", "authority", "delay", "guard", "recovery"))
    tau = float(plant.tau)
    sensor: Sensor = NoisySensor(float(noise_sigma), np.random.default_rng(seed))
    m = _plain(f.get("measurement"))
    check_keys("measurement", m, ("kind", "time", "state", "size", "sigma"))
    if m.get("kind") is not None:
        kind = m["kind"]
        if isinstance(kind, float) and math.isnan(kind):  # `kind=nan` on the command line arrives as a float
            kind = "nan"
        if kind not in ("nan", "outlier"):
            raise ValueError(f"faults.measurement.kind={kind!r}; expected null, 'nan' or 'outlier'")
        state = _index("measurement.state", m.get("state", 0), tuple(system.state_names))
        jump = 0.0
        if kind == "outlier":
            sigma = m.get("sigma") if m.get("sigma") is not None else noise_sigma
            sigma = _number("measurement.sigma", sigma, "a sigma > 0 (or noise_sigma > 0)", 1e-300)
            jump = _number("measurement.size", m.get("size", 10.0), "a number of sigmas") * sigma
        step = _step("measurement.time", m.get("time"), tau)
        sensor = BadSample(sensor, step, state, kind, jump, system.state_names[state])
    d = _plain(f.get("delay"))
    check_keys("delay", d, ("time", "duration"))
    if d.get("time") is not None:
        start = _step("delay.time", d["time"], tau)
        end = 10**9 if d.get("duration") is None else start + max(_step("delay.duration", d["duration"], tau), 1)
        sensor = DelayedSensor(sensor, start, end)
    a = _plain(f.get("authority"))
    check_keys("authority", a, ("joint", "time", "duration", "gain"))
    if a.get("joint") is not None:
        j = _index("authority.joint", a["joint"], tuple(system.input_names))
        start = _step("authority.time", a.get("time"), tau)
        end = start + max(_step("authority.duration", a.get("duration"), tau), 1)
        gain = _number("authority.gain", a.get("gain", 0.5), "a finite gain (0.5: half the input)")
        plant = AuthorityLoss(plant, j, gain, start, end, system.input_names[j])
    p = _plain(f.get("payload"))
    check_keys("payload", p, ("time", "mass", "mass_scale"))
    if p.get("time") is not None:
        at = _step("payload.time", p["time"], tau)
        second, what = changed_plant(system, plant_cfg, robots, tau, p)
        plant = PlantSwitch(plant, second, at, what)
    r = _plain(f.get("recovery"))
    check_keys("recovery", r, tuple(RECOVERY_DEFAULTS))
    r = {**RECOVERY_DEFAULTS, **{k: v for k, v in r.items() if v is not None}}
    recovery = Recovery(
        _number("recovery.window", r["window"], "an integer >= 1", 1, integer=True),  # type: ignore[arg-type]
        _number("recovery.factor", r["factor"], "a factor >= 1", 1.0),
        _number("recovery.tolerance", r["tolerance"], "an error >= 0 in rad", 0.0),
        _number("recovery.samples", r["samples"], "an integer >= 0", 0, integer=True),  # type: ignore[arg-type]
    )
    return FaultPlan(plant, sensor, build_guard(_plain(f.get("guard")), predict), recovery)


def changed_plant(system: System, plant_cfg: Any, robots: Any, tau: float, p: Mapping[str, Any]) -> tuple[Plant, str]:
    """The plant after the payload change: MuJoCo with the tip payload's new mass, scipy with a new mass_scale."""
    from pinnmpc.plant.build import make_plant

    pc = _plain(plant_cfg)
    if pc.get("kind", "scipy") == "mujoco":
        mass = _number("payload.mass", p.get("mass"), "a payload mass >= 0 in kg (plant=mujoco)", 0.0)
        known = copy.deepcopy(_plain(robots))
        name = pc.get("robot") or "pinnmpc_fault"
        robot = dict(known.get(name) or {})
        payload = dict(robot.get("payload") or {})
        before = float(payload.get("mass", 0.0))
        robot["payload"] = {**payload, "mass": mass}
        known[name] = robot
        second = make_plant(system, OmegaConf.create({**pc, "robot": name}), tau, known)
        return second, f"payload {before:g} -> {mass:g} kg"
    scale = _number("payload.mass_scale", p.get("mass_scale"), "a mass scale > 0 (plant=scipy)", 1e-12)
    before = float(pc.get("mass_scale", 1.0))
    second = make_plant(system, OmegaConf.create({**pc, "mass_scale": scale}), tau, robots)
    return second, f"mass_scale {before:g} -> {scale:g}"
