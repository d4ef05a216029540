"""Built-in reference trajectories, described as data in conf/system/<name>.yaml (`references:`)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from pinnmpc.references.data import Reference, ReferenceError

BUILTIN_DT = 0.01  # s, sampling of the built-in references; fine enough to resample to any controller step


# ---------------------------------------------------------------------------------------------------------------
# Built-in references, described as data in conf/system/<name>.yaml (`references:`), one entry per name:
#   {kind: waypoints, joints: [{q: [...], durations: [...]}, ...]}: each joint a chain of quintic (minimum-jerk)
#       blends between positions reached at rest, so position, velocity and acceleration are continuous;
#   {kind: sine, amplitude: [...], frequency: [...], offset: [...], duration: s}: sinusoids per joint;
#   {kind: random, moves: n, duration: s, fraction: f}: quintic moves between random waypoints in the middle
#       fraction f of the state box (name it `random-<seed>` to pick the seed, default 0);
#   {kind: driven, moves, duration, fraction, bandwidth: rad/s, damping}: the true system driven around such a
#       random path by a loose feedback (pinnmpc/references/driven.py): a motion the true model makes with in-box
#       inputs.


@dataclass(frozen=True)
class Waypoints:
    """One joint's path: positions q reached at rest, and the duration of each blend between consecutive ones."""

    q: tuple[float, ...]
    durations: tuple[float, ...]


def quintic_blend(t: np.ndarray, waypoints: Waypoints) -> tuple[np.ndarray, np.ndarray]:
    """Position and exact velocity of minimum-jerk blends, held at the ends, so references are dynamically smooth."""
    q = np.asarray(waypoints.q, dtype=np.float64)
    d = np.asarray(waypoints.durations, dtype=np.float64)
    if len(d) != len(q) - 1 or np.any(d <= 0):
        raise ReferenceError(f"waypoints {waypoints}: expected len(q) - 1 positive durations")
    knots = np.concatenate([[0.0], np.cumsum(d)])
    seg = np.clip(np.searchsorted(knots, t, side="right") - 1, 0, len(d) - 1)
    s = np.clip((t - knots[seg]) / d[seg], 0.0, 1.0)
    dq = q[seg + 1] - q[seg]
    pos = q[seg] + dq * s**3 * (10.0 - 15.0 * s + 6.0 * s**2)
    vel = dq / d[seg] * 30.0 * s**2 * (1.0 - s) ** 2
    return pos, vel


def _grid(duration: float) -> np.ndarray:
    """Built-in sample times that hit the end time exactly rather than stopping a float step short."""
    return np.arange(round(duration / BUILTIN_DT) + 1) * BUILTIN_DT


def waypoint_reference(name: str, joints: Sequence[Waypoints]) -> Reference:
    """Every joint from its waypoint table; shorter ones hold their last position until the longest ends."""
    t = _grid(max(sum(w.durations) for w in joints))
    pos, vel = zip(*(quintic_blend(t, w) for w in joints))
    return Reference(t=t, x=np.stack([*pos, *vel], axis=1), name=f"builtin:{name}")


def sine_reference(
    name: str, amplitude: Sequence[float], frequency: Sequence[float], offset: Sequence[float], duration: float
) -> Reference:
    """Sinusoids with analytic velocities: a reference that never rests, unlike the waypoint ones."""
    sizes = {key: np.size(v) for key, v in (("amplitude", amplitude), ("frequency", frequency), ("offset", offset))}
    if len(set(sizes.values())) > 1:
        found = ", ".join(f"{key} {n}" for key, n in sizes.items())
        raise ReferenceError(f"built-in reference {name!r}: {found} entries; expected one per joint in each")
    t = _grid(duration)
    a, f, c = (np.asarray(v, dtype=np.float64)[None, :] for v in (amplitude, frequency, offset))
    w = 2.0 * math.pi * f
    x = np.concatenate([a * np.sin(w * t[:, None]) + c, a * w * np.cos(w * t[:, None])], axis=1)
    return Reference(t=t, x=x, name=f"builtin:{name}")


def random_waypoints(
    low: Sequence[float], high: Sequence[float], seed: int, moves: int, duration: float, fraction: float
) -> list[Waypoints]:
    """Per joint: random waypoints in the middle `fraction` of its position range, `duration` s apart."""
    lo, hi = np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64)
    mid, half = (lo + hi) / 2, fraction * (hi - lo) / 2
    q = mid + half * np.random.default_rng(seed).uniform(-1.0, 1.0, size=(int(moves) + 1, len(lo)))
    q[0] = mid  # start at rest in the middle, where every run of this reference begins
    return [Waypoints(tuple(q[:, j]), (float(duration),) * int(moves)) for j in range(len(lo))]


def random_reference(
    name: str, low: Sequence[float], high: Sequence[float], seed: int, moves: int, duration: float, fraction: float
) -> Reference:
    """Quintic moves of every joint between random waypoints in the middle `fraction` of its position range."""
    return waypoint_reference(name, random_waypoints(low, high, seed, moves, duration, fraction))


def driven_reference(
    name: str, system: Any, joints: Sequence[Waypoints], bandwidth: object, damping: object
) -> Reference:
    """The true system driven around the waypoint path by a loose feedback (pinnmpc/references/driven.py), sampled."""
    from pinnmpc.references.driven import check_gains, drive

    gains = check_gains(name, bandwidth, damping)
    duration = max(sum(w.durations) for w in joints)
    t = _grid(duration)

    def path(time: float) -> tuple[np.ndarray, np.ndarray]:
        """The path's joint positions and velocities at one time."""
        pos, vel = zip(*(quintic_blend(np.array([time]), w) for w in joints))
        return np.concatenate(pos), np.concatenate(vel)

    return Reference(t=t, x=drive(system, path, duration, t, *gains), name=f"builtin:{name}")


def builtin_reference(
    name: str,
    specs: dict[str, Any],
    position_box: tuple[Sequence[float], Sequence[float]] | None = None,
    system: Any = None,
) -> Reference:
    """A reference described in the system's config (`references:`), so closed loops run without data files;
    a driven one also needs the system it drives."""
    spec, seed = specs.get(name), None
    base, _, suffix = name.rpartition("-")
    if spec is None and suffix.isdigit() and base in specs:
        spec, seed = specs[base], int(suffix)
    if not isinstance(spec, dict):
        raise ReferenceError(f"unknown built-in reference {name!r}; expected one of: {', '.join(specs)}")
    kind = spec.get("kind")
    try:
        if kind == "waypoints":
            joints = [Waypoints(tuple(j["q"]), tuple(j["durations"])) for j in spec["joints"]]
            return waypoint_reference(name, joints)
        if kind == "sine":
            keys = ("amplitude", "frequency", "offset", "duration")
            return sine_reference(name, *(spec[k] for k in keys))
        if kind in ("random", "driven"):
            if position_box is None or (kind == "driven" and system is None):
                raise ReferenceError(f"built-in reference {name!r} needs the system (its joint range)")
            seed = int(spec.get("seed", 0)) if seed is None else seed
            keys = (spec["moves"], spec["duration"], spec.get("fraction", 0.5))
            if kind == "random":
                return random_reference(name, *position_box, seed, *keys)
            joints = random_waypoints(*position_box, seed, *keys)
            return driven_reference(name, system, joints, spec["bandwidth"], spec["damping"])
    except (KeyError, TypeError) as e:
        raise ReferenceError(f"built-in reference {name!r}: malformed spec {spec} ({e!r})") from None
    except ValueError as e:
        raise ReferenceError(str(e)) from None
    raise ReferenceError(f"built-in reference {name!r}: kind={kind!r}; expected waypoints, sine, random or driven")
