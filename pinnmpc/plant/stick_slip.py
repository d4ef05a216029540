"""Coulomb friction with a sign(v) term, integrated with its switches located (a Filippov solution).

An adaptive solver stepping across sign(v) at rest chatters: every step that straddles v = 0 sees the friction
flip, the error estimate fails, and the step shrinks until the flips fit the tolerance. The plant then needs
thousands of rhs evaluations per period while the joint merely sticks. Here each such joint has a mode: sliding
(+1 or -1, sign(v) fixed, until v reaches 0: an event) or stuck (v held at 0 by the friction fraction s in
[-1, 1] that cancels its acceleration, until |s| would exceed 1: an event). The rhs is smooth inside each mode,
so the same solve_ivp method takes its ordinary steps between the events.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from scipy.integrate import solve_ivp

START_SPEED = 1e-12  # rad/s a joint that starts to slide from rest starts with: far below any solver tolerance


class ChatterError(Exception):
    """A plain step saw a sign(v) joint's velocity flip too often: integrate it by modes instead."""


def coulomb_joints(system: Any) -> tuple[int, ...]:
    """Joints whose rhs has a discontinuous sign(v) friction term (none unless the system names them)."""
    return tuple(getattr(system, "coulomb_joints", ()))


def flip_counter(fun: Callable, velocities: list[int], max_flips: int) -> Callable:
    """fun, raising ChatterError once the velocities' signs have flipped more than max_flips times between calls."""
    last = [0.0] * len(velocities)  # the last nonzero velocity seen, per joint (plain floats: this runs every call)
    flips = 0

    def counted(t: float, x: np.ndarray, *args: Any) -> np.ndarray:
        nonlocal flips
        for i, k in enumerate(velocities):
            v = float(x[k])
            if v * last[i] < 0.0:
                flips += 1
            if v != 0.0:
                last[i] = v
        if flips > max_flips:
            raise ChatterError
        return fun(t, x, *args)

    return counted


def _holding_signs(system: Any, x: np.ndarray, u: np.ndarray, signs: np.ndarray, stuck: np.ndarray) -> np.ndarray:
    """signs with the stuck joints' entries set to the friction fractions that hold their accelerations at 0."""
    idx = np.flatnonzero(stuck)
    if idx.size == 0:
        return signs
    acc = (system.nq + np.asarray(coulomb_joints(system)))[idx]
    base = signs.copy()
    base[idx] = 0.0
    a0 = system.rhs_coulomb(x, u, base)[acc]
    columns = []
    for k in idx:  # the rhs is affine in each fraction: one evaluation per stuck joint gives its column
        unit = base.copy()
        unit[k] = 1.0
        columns.append(system.rhs_coulomb(x, u, unit)[acc] - a0)
    out = base
    out[idx] = np.linalg.solve(np.stack(columns, axis=1), -a0)
    return out


def _mode_at_rest(system: Any, x: np.ndarray, u: np.ndarray, signs: np.ndarray, k: int) -> float:
    """Mode of joint k at v = 0 (the others as given): 0 when friction can hold it, else the sign it slides with."""
    stuck = np.zeros(len(signs), dtype=bool)
    stuck[k] = True
    s = _holding_signs(system, x, u, signs, stuck)[k]
    return 0.0 if abs(s) <= 1.0 else float(np.sign(s))


def stick_slip_step(
    system: Any, x0: np.ndarray, u: np.ndarray, tau: float, method: str, rtol: float, atol: float, max_events: int
) -> np.ndarray:
    """One zero-hold period with every sign(v) joint integrated by modes; raises RuntimeError past max_events."""
    joints = np.asarray(coulomb_joints(system))
    vel = system.nq + joints
    x = np.array(x0, dtype=np.float64)
    modes = np.sign(x[vel])  # +1 / -1 sliding, 0 stuck
    for k in np.flatnonzero(modes == 0):
        modes[k] = _mode_at_rest(system, x, u, modes, k)
    t = 0.0
    for _ in range(max_events):
        stuck = modes == 0
        x[vel[stuck]] = 0.0
        starting = ~stuck & (x[vel] * modes <= 0.0)  # sliding from rest: off zero, or its rest event fires at once
        x[vel[starting]] = modes[starting] * START_SPEED

        def fun(_t: float, y: np.ndarray, stuck: np.ndarray = stuck, modes: np.ndarray = modes) -> np.ndarray:
            """The rhs inside the current modes: stuck joints keep their position and zero velocity."""
            dy = system.rhs_coulomb(y, u, _holding_signs(system, y, u, modes, stuck))
            dy[joints[stuck]] = 0.0
            dy[vel[stuck]] = 0.0
            return dy

        events = [_event(system, u, modes, stuck, k) for k in range(len(joints))]
        sol = solve_ivp(fun, (t, tau), x, method=method, rtol=rtol, atol=atol, events=events)
        if not sol.success:
            raise RuntimeError(sol.message)
        if sol.status == 0:
            return sol.y[:, -1]
        k = next(i for i, te in enumerate(sol.t_events) if len(te))
        t, x = float(sol.t_events[k][0]), np.array(sol.y_events[k][0])
        if stuck[k]:  # friction can no longer hold it: slide the way the fraction ran out
            modes[k] = float(np.sign(_holding_signs(system, x, u, modes, stuck)[k]))
        else:  # it came to rest: stick, or reverse
            x[vel[k]] = 0.0
            modes[k] = _mode_at_rest(system, x, u, modes, k)
    raise RuntimeError(f"more than {max_events} stick-slip switches in one period of {tau} s")


def _event(system: Any, u: np.ndarray, modes: np.ndarray, stuck: np.ndarray, k: int) -> Callable:
    """Terminal event of joint k: a sliding joint reaches v = 0; a stuck one needs a friction fraction beyond 1."""
    vel = system.nq + coulomb_joints(system)[k]

    if stuck[k]:

        def breakaway(_t: float, y: np.ndarray) -> float:
            """|s| - 1 of the holding fraction: crosses 0 upward when friction can no longer hold."""
            return abs(_holding_signs(system, y, u, modes, stuck)[k]) - 1.0

        breakaway.terminal, breakaway.direction = True, 1.0
        return breakaway

    def rest(_t: float, y: np.ndarray) -> float:
        """The velocity, which crosses 0 against the sliding direction when the joint comes to rest."""
        return float(y[vel])

    rest.terminal, rest.direction = True, -float(modes[k])
    return rest
