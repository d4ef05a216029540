"""Classical identification: the model's physical coefficients fitted to robot logs by bounded linear least squares.

The arm's equation M(q) dv/dt + h(q, v) = torque is linear in every coefficient fitted here: per-joint viscous D and
Coulomb C (torque = u - D v - C tanh(s v)) or servo gain K, damping D and Coulomb C (torque = g0(q) + K (u - v) - D v
- C tanh(s v)), a point mass m_p at a given place (M and h gain m_p times those of a unit mass) and per-joint armature
A (on M's diagonal). The fit integrates that equation over each fine interval of a hold period instead of
differentiating the samples: the interval's velocity change carries the inertia (A dv exactly), its position change
the viscous term (D dq exactly) and the input is held, so only the slowly varying M(q), h and the Coulomb term are
averaged over the interval's two ends.
Differences of the fine samples would not do: planar3's velocities relax within milliseconds after each input step,
below a 10 ms fine step, and the acceleration estimates were off by as much as their size. One bounded least-squares
solve (every coefficient >= 0) gives the fit, with no iterations or starting guess. A joint's equation counts only
where it moves faster than min_speed: dry friction (which sticks) has no smooth counterpart, and while sliding it is
a constant torque against the motion, which the Coulomb term C tanh(s v) then absorbs (C fitted = C + dry friction).
The point mass's place is fitted too where asked: what a unit mass adds is a quadratic polynomial in its place (its
spatial inertia is linear in 1, c and c c^T), so ten evaluations of the arm give it at every place, and a small
search over the place, each trial one bounded linear solve for the rest, finds where the load sits.
One-period predictions of the fitted model (RK4) against the logged next states are reported beside the nominal's.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from scipy.optimize import least_squares, lsq_linear

from pinnmpc.plant.integrators import rk4_fixed
from pinnmpc.robot_data.episodes import check_enough
from pinnmpc.robot_data.logs import RobotLog, first_index, period_starts
from pinnmpc.systems.urdf import Payload, RigidArm
from pinnmpc.systems.urdf_files import payload_place

KEYS = ("viscous", "coulomb", "servo_gain", "payload", "payload_pos", "armature", "load")  # what can be fitted
COMMANDS = ("held", "reported")  # what drives each fine interval: the period's input held, or the command the robot
#   reported (the log's command_fine) at the interval's end, against the velocity at its start
# Places around the start (in units of the stencil's size) whose unit-mass columns fix the quadratic in c exactly.
STENCIL = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [-1, 0, 0], [0, -1, 0], [0, 0, -1], [1, 1, 0],
                    [1, 0, 1], [0, 1, 1]], dtype=float)  # fmt: skip


@dataclass
class Intervals:
    """Fine intervals inside hold periods: both ends' q, v (n, 2, nq), their length dt (n,), the input u (n, nu) and
    whether each joint's servo follows u there (n, nq): false while a robot still ramps towards the command;
    feedback (n, nq): the velocity a servo's term K (u - v) takes, None: the interval's mean (its dq / dt)."""

    q: np.ndarray
    v: np.ndarray
    dt: np.ndarray
    u: np.ndarray
    settled: np.ndarray
    feedback: np.ndarray | None = None


@dataclass
class Fit:
    """The fitted coefficients, the fitted system and how well it explains the logs."""

    system: RigidArm
    values: dict[str, Any]  # viscous, coulomb / servo_gain, payload_mass, armature (as fitted or kept)
    fitted: list[str]  # which of KEYS were fitted
    samples: int  # equations used (one per joint and fine interval where the joint moves faster than min_speed)
    torque_rms: list[float]  # per joint, N m: the interval-mean torque residual of the fitted model
    nominal_torque_rms: list[float]  # the same for the nominal model
    prediction_rmse: list[float]  # per state: one-period RK4 predictions of the fitted model vs the logged next states
    nominal_prediction_rmse: list[float]  # the same for the nominal model


def intervals(
    logs: Sequence[RobotLog],
    max_samples: int | None = None,
    seed: int = 0,
    settle: float = 0.0,
    command: str = "held",
) -> Intervals:
    """Every fine interval inside a hold period of the logs (control-rate periods where a log has no fine part), up
    to max_samples of them drawn at random. A joint's servo counts as settled (Intervals.settled) in intervals that
    begin `settle` s or more after their period, and where a log's meta gives the robot's `command_acceleration`
    (rad/s^2 per joint: franky ramps each velocity command at most that fast) only once the ramp from the period's
    start velocity to the command has had time to end too. command="reported": each interval's input is instead the
    command the robot reported at its end (the target its servo tracked over that tick), fed back against the
    velocity at its start, and no ramp is left out (the logs' fine step must be the servo's tick)."""
    if command not in COMMANDS:
        raise ValueError(f"command={command!r}; expected one of {list(COMMANDS)}")
    if command == "reported":
        return _reported_intervals(logs, max_samples, seed, settle)
    parts = []
    for log in logs:
        fine = log.fine
        n = len(log.meta["input_names"])
        t, x, ep = (log.t_fine, log.x_fine, log.episode_fine) if fine > 1 else (log.t, log.x, log.episode)
        first = np.r_[True, ep[1:] != ep[:-1]]
        begin = np.maximum.accumulate(np.where(first, np.arange(len(ep)), 0))
        start = np.flatnonzero(((np.arange(len(ep)) - begin) % fine == 0) & np.r_[ep[1:] == ep[:-1], False])
        u = log.u[np.r_[log.episode[1:] == log.episode[:-1], False]]
        accel = log.meta.get("command_acceleration")
        ramp = np.abs(u - x[start, n:]) / np.asarray(accel, dtype=float) if accel else np.zeros_like(u)
        ramp = ramp + settle - 1e-9 * log.tau  # a sub-time on the settle time counts
        for a in range(fine):
            i = start + a
            ends = np.stack((x[i], x[i + 1]), axis=1)
            parts.append((ends[..., :n], ends[..., n:], t[i + 1] - t[i], u, (t[i] - t[start])[:, None] >= ramp))
    return _drawn(Intervals(*(np.concatenate(p) for p in zip(*parts))), max_samples, seed)


def _drawn(s: Intervals, max_samples: int | None, seed: int) -> Intervals:
    """s, or max_samples of its intervals drawn at random (in their order)."""
    if max_samples is None or len(s.q) <= max_samples:
        return s
    keep = np.sort(np.random.default_rng(seed).choice(len(s.q), max_samples, replace=False))
    return Intervals(*(None if a is None else a[keep] for a in dataclasses.astuple(s)))


def _reported_intervals(logs: Sequence[RobotLog], max_samples: int | None, seed: int, settle: float) -> Intervals:
    """intervals() of command="reported": every fine interval of an episode, driven by the reported command."""
    parts = []
    for path, log in enumerate(logs):
        if log.command_fine is None or log.fine < 2:
            raise ValueError(
                f"command=reported: log {path} has no reported commands (command_fine, fine={log.fine}); expected "
                "logs of plant=franka collected with fine > 1, or command=held"
            )
        n, t, x, ep = len(log.meta["input_names"]), log.t_fine, log.x_fine, log.episode_fine
        i = np.flatnonzero(period_starts(ep))  # every fine sample with a next one in its episode
        into = (t[i] - t[first_index(ep)[i]]) % log.tau  # how far into its period each interval begins
        ends = np.stack((x[i], x[i + 1]), axis=1)
        settled = np.broadcast_to((into >= settle - 1e-9 * log.tau)[:, None], (len(i), n))
        parts.append((ends[..., :n], ends[..., n:], t[i + 1] - t[i], log.command_fine[i + 1], settled, x[i, n:]))
    return _drawn(Intervals(*(np.concatenate(p) for p in zip(*parts))), max_samples, seed)


def _terms(system: RigidArm, q: np.ndarray, v: np.ndarray, chunk: int = 4096) -> tuple[np.ndarray, ...]:
    """M (B, n, n), h (B, n) and the compensated gravity g (B, n) by adam in chunks, mass_scale applied to all."""
    out: list[list[np.ndarray]] = [[], [], []]
    with torch.no_grad():
        for s in range(0, len(q), chunk):
            qs, vs = torch.from_numpy(q[s : s + chunk]), torch.from_numpy(v[s : s + chunk])
            for k, term in enumerate(system.dynamics_terms(qs, vs)):
                out[k].append(np.broadcast_to(term.numpy(), (len(qs), *term.shape[1:])))
    ms = system.mass_scale
    return np.concatenate(out[0]), ms * np.concatenate(out[1]), ms * np.concatenate(out[2])


def _interval_terms(system: RigidArm, s: Intervals) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """M, h and g of the system averaged over each interval's two ends: (n, nq, nq), (n, nq), (n, nq)."""
    nq = system.nq
    m, h, g = _terms(system, s.q.reshape(-1, nq), s.v.reshape(-1, nq))
    return m.reshape(-1, 2, nq, nq).mean(1), h.reshape(-1, 2, nq).mean(1), g.reshape(-1, 2, nq).mean(1)


def _unit_column(base: RigidArm, s: Intervals, payload: Payload, m0: np.ndarray, h0: np.ndarray) -> np.ndarray:
    """(n, nq): what a unit point mass at payload's place adds to each interval's torque equation."""
    unit = dataclasses.replace(base, payload=dataclasses.replace(payload, mass=1.0))
    m1, h1, _ = _interval_terms(unit, s)
    return np.einsum("bij,bj->bi", m1 - m0, s.v[:, 1] - s.v[:, 0]) / s.dt[:, None] + h1 - h0


def _load_column(base: RigidArm, s: Intervals, load: Payload, terms: tuple[np.ndarray, ...]) -> np.ndarray:
    """(n, nq): what a unit point mass at load's place, which the servo compensates with the arm, adds to each
    interval's torque equation: its inertia, and whatever of its bias the servo leaves (gravity compensation: its
    Coriolis torques)."""
    m0, h0, g0 = terms
    m1, h1, g1 = _interval_terms(dataclasses.replace(base, load=dataclasses.replace(load, mass=1.0)), s)
    return np.einsum("bij,bj->bi", m1 - m0, s.v[:, 1] - s.v[:, 0]) / s.dt[:, None] + (h1 - g1) - (h0 - g0)


def _quadratic(c: np.ndarray) -> np.ndarray:
    """The ten monomials of degree <= 2 in c (..., 3): a point mass's spatial inertia is linear in them."""
    x, y, z = np.moveaxis(c, -1, 0)
    return np.stack([np.ones_like(x), x, y, z, x * x, y * y, z * z, x * y, x * z, y * z], axis=-1)


def place_columns(
    system: RigidArm, s: Intervals, payload: Payload, size: float, terms: tuple[np.ndarray, ...] | None = None
) -> tuple[str, np.ndarray, Any]:
    """The payload's link, its start place (3,) and column(c): the unit-mass column (n * nq,) at any place c in that
    link's frame, exact from the stencil of places around the start (size: the stencil's spacing, m); terms: the
    bare arm's _interval_terms where already computed."""
    base = _bare(system)
    link, start = payload_place(base.model_urdf, payload, system.tip_frame, system.joints)
    c0 = np.asarray(start)
    m0, h0, _ = terms or _interval_terms(base, s)
    at = [_unit_column(base, s, Payload(1.0, tuple((c0 + size * d).tolist()), link), m0, h0) for d in STENCIL]
    coef = np.linalg.solve(_quadratic(STENCIL), np.stack([a.reshape(-1) for a in at]))
    return link, c0, lambda c: _quadratic((np.asarray(c) - c0) / size) @ coef


def _bare(system: RigidArm) -> RigidArm:
    """The arm (its load kept) without payload and armature and with unscaled friction: the fit's starting point."""
    return dataclasses.replace(system, payload=None, armature=(), friction_scale=1.0)


def regression(
    system: RigidArm,
    s: Intervals,
    fit: Sequence[str],
    payload: Payload,
    terms: tuple[np.ndarray, ...] | None = None,
    load: Payload | None = None,
) -> tuple[np.ndarray, np.ndarray, list[str], np.ndarray]:
    """A theta = b, the equation integrated over each interval and divided by its length (torque units) for the
    coefficients named in fit (rows: interval-major, joint-minor), the column names and each row's joint;
    coefficients not fitted keep their nominal value (payload and armature: none; the system's load kept), a fitted
    load sits at `load`'s place."""
    base = _bare(system)
    n, servo = system.nq, system.actuation == "velocity_servo"
    dq, dv, dt = s.q[:, 1] - s.q[:, 0], s.v[:, 1] - s.v[:, 0], s.dt[:, None]
    m0, h0, g0 = terms or _interval_terms(base, s)
    rhs = (g0 if servo else s.u) - np.einsum("bij,bj->bi", m0, dv) / dt - h0  # what the fitted terms must make up
    cols: dict[str, np.ndarray] = {}
    if "payload" in fit:  # where its place is searched, the search fills the column in
        cols["payload_mass"] = np.zeros_like(dv) if "payload_pos" in fit else _unit_column(base, s, payload, m0, h0)
    if "load" in fit:
        cols["load_mass"] = _load_column(base, s, load or Payload(0.0), (m0, h0, g0))
    feedback = dq / dt if s.feedback is None else s.feedback  # the velocity the servo's term takes
    per_joint = {
        "armature": dv / dt,
        "viscous": dq / dt,
        "coulomb": np.tanh(system.coulomb_slope * s.v).mean(1),
        "servo_gain": feedback - s.u,
    }
    eye = np.eye(n)
    for key, value in per_joint.items():
        if key not in fit:
            if key in ("viscous", "coulomb", "servo_gain") and getattr(system, key):
                rhs = rhs - system.friction_scale * np.asarray(getattr(system, key)) * value
            continue
        for j in range(n):
            cols[f"{key}[{j}]"] = value * eye[j]
    names = list(cols)
    a = np.stack([cols[k] for k in names], axis=-1).reshape(-1, len(names)) if names else np.zeros((rhs.size, 0))
    return a, rhs.reshape(-1), names, np.tile(np.arange(n), len(s.q))


def identify(
    system: RigidArm,
    logs: Sequence[RobotLog],
    fit: Sequence[str],
    payload: Payload | None = None,
    *,
    name: str | None = None,
    max_samples: int | None = None,
    min_speed: float = 0.0,
    place_range: float = 0.3,
    validation_periods: int = 1000,
    rk4_steps: int = 50,
    seed: int = 0,
    settle: float = 0.0,
    load: Payload | None = None,
    command: str = "held",
) -> Fit:
    """Fit the named coefficients (of KEYS) to the logs; payload gives the mass's place (mass ignored; None: the
    tip, as the MuJoCo robots' convention), with "payload_pos" where the search for it starts (within place_range
    m per axis); load the place of a mass the servo compensates with the arm ("load": its mass fitted, in place of
    the system's load; None: the system's load's place, else the tip). A joint's equation counts only where its
    speed exceeds min_speed at both ends of the interval: slower, a real arm's dry friction sticks and slips, which
    no smooth model follows. Intervals that begin less than `settle` s into their period are left out (a command
    reaching the servo late or ramped: plant=franka), and with command="held" those while a logged command ramp
    (meta `command_acceleration`) runs; command="reported" drives each interval by the command the robot reported
    (intervals())."""
    unknown = [k for k in fit if k not in KEYS]
    if unknown:
        raise ValueError(f"fit {unknown}; expected some of {list(KEYS)}")
    if "payload_pos" in fit and "payload" not in fit:
        raise ValueError("fit.payload_pos=true needs fit.payload=true: the place is searched with the mass")
    if not 0 <= settle < system.tau:
        raise ValueError(f"settle={settle}; expected 0 <= settle < the control period {system.tau} s")
    if "payload_pos" in fit and not (math.isfinite(place_range) and place_range > 0):
        raise ValueError(f"payload.range={place_range!r}; expected a finite number > 0 (m)")
    friction = ("servo_gain", "viscous", "coulomb") if system.actuation == "velocity_servo" else ("viscous", "coulomb")
    allowed = (*friction, "payload", "payload_pos", "armature", "load")
    fit = [k for k in fit if k in allowed]
    if not fit:
        raise ValueError(f"nothing to fit for actuation {system.actuation}; expected some of {list(allowed)}")
    payload = payload or Payload(0.0)
    load = load or system.load or Payload(0.0)
    if "load" in fit:  # the fitted load takes the system's place
        system = dataclasses.replace(system, load=None)
    s = intervals(logs, max_samples, seed, settle, command)
    terms = _interval_terms(_bare(system), s)  # M, h, g of the bare arm: the regression's and the place search's
    a, b, names, joint = regression(system, s, fit, payload, terms, load)
    used = ((np.abs(s.v).min(axis=1) > min_speed) & s.settled).reshape(-1)
    check_enough(int(used.sum()) // system.nq, 20 * len(names), f"the logs (joints above min_speed={min_speed})",
                 tau=system.tau, fine=logs[0].fine, t_max=system.tau / logs[0].fine)  # fmt: skip
    weight = used / _torque_scale(system)[joint]  # each joint's equation relative to its torque range
    if "payload_pos" in fit:
        k = names.index("payload_mass")
        payload = _search_place(place_columns(system, s, payload, place_range, terms), a, b, weight, k, place_range)
    theta = _bounded_fit(a, b, weight)
    values = _values(system, names, theta, fit)
    if "payload_pos" in fit:
        values["payload_pos"] = list(payload.pos)
    fitted = fitted_system(system, values, payload, name, load)
    mask = used.reshape(-1, system.nq)
    res, res0 = ((a @ th - b).reshape(-1, system.nq) for th in (theta, _nominal_theta(system, names)))
    pred, pred0 = (one_period_rmse(m, logs, validation_periods, rk4_steps, seed) for m in (fitted, system))
    return Fit(fitted, values, list(fit), int(used.sum()), _rms(res, mask), _rms(res0, mask), pred, pred0)


def _bounded_fit(a: np.ndarray, b: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """theta >= 0 minimising |weight (a theta - b)|, each column scaled to unit size for the solver."""
    aw = a * weight[:, None]
    scale = np.maximum(np.sqrt((aw**2).mean(axis=0)), 1e-300)
    return lsq_linear(aw / scale, b * weight, bounds=(0.0, np.inf), method="bvls", lsmr_tol="auto").x / scale


def _search_place(
    columns: tuple[str, np.ndarray, Any], a: np.ndarray, b: np.ndarray, weight: np.ndarray, k: int, size: float
) -> Payload:
    """The point mass's place (within size per axis of the start) that explains the logs best, the rest refitted at
    each trial place (columns: place_columns'); a's column k (the payload's) is left at that place."""
    link, c0, column = columns

    def residual(c: np.ndarray) -> np.ndarray:
        a[:, k] = column(c)
        return (a @ _bounded_fit(a, b, weight) - b) * weight

    found = least_squares(residual, c0, bounds=(c0 - size, c0 + size), x_scale=size, diff_step=1e-3)
    a[:, k] = column(found.x)
    return Payload(0.0, tuple(float(v) for v in found.x), link)


def _nominal_theta(system: RigidArm, names: list[str]) -> np.ndarray:
    """The nominal model's value of each column: its scaled friction or gain, no payload, no armature."""
    out = []
    for key in names:
        base, _, j = key.partition("[")
        value = getattr(system, base, ()) if base in ("viscous", "coulomb", "servo_gain") else ()
        out.append(system.friction_scale * value[int(j[:-1])] if value else 0.0)
    return np.asarray(out)


def _rms(r: np.ndarray, mask: np.ndarray | None = None) -> list[float]:
    """Root mean square per column (over the entries mask keeps; nan where it keeps none)."""
    mask = np.ones(r.shape, dtype=bool) if mask is None else mask
    count = mask.sum(axis=0)
    return [float(v) for v in np.sqrt(np.where(mask, r**2, 0.0).sum(axis=0) / np.maximum(count, 1))]


def residual_fraction(system: RigidArm, fit: Fit) -> list[float]:
    """The fit's torque residual per joint over the joint's torque scale: near zero when the robot lies in the
    model's class (what is left is the logs' integration and stick-slip), a few percent when it has effects no
    coefficient here expresses."""
    return (np.asarray(fit.torque_rms) / _torque_scale(system)).tolist()


def _torque_scale(system: RigidArm) -> np.ndarray:
    """A typical torque per joint: half the input range (servos: the gain times it)."""
    half = (np.asarray(system.input_box.high) - np.asarray(system.input_box.low)) / 2
    if system.actuation == "velocity_servo":
        half = half * np.asarray(system.servo_gain)
    return np.maximum(half, 1e-12)


def _values(system: RigidArm, names: list[str], theta: np.ndarray, fit: Sequence[str]) -> dict[str, Any]:
    """The coefficients by name: fitted ones from theta, the rest the nominal model's (scaled friction included)."""
    got = dict(zip(names, theta.tolist()))
    n, f = system.nq, system.friction_scale
    out: dict[str, Any] = {}
    for key in ("viscous", "coulomb", "servo_gain", "armature"):
        if key in fit:
            out[key] = [got[f"{key}[{j}]"] for j in range(n)]
        elif key == "armature":
            out[key] = [0.0] * n
        elif getattr(system, key):
            out[key] = [f * v for v in getattr(system, key)]
    out["payload_mass"] = got.get("payload_mass", 0.0)
    if "load" in fit:
        out["load_mass"] = got["load_mass"]
    return out


def fitted_system(
    system: RigidArm, values: dict[str, Any], payload: Payload, name: str | None = None, load: Payload | None = None
) -> RigidArm:
    """The nominal arm with the fitted coefficients (friction scale 1, payload, load and armature where nonzero)."""
    changes: dict[str, Any] = {"friction_scale": 1.0, "name": name or system.name}
    for key in ("viscous", "coulomb", "servo_gain"):
        if key in values:
            changes[key] = tuple(values[key])
    mass = values.get("payload_mass", 0.0)
    changes["payload"] = dataclasses.replace(payload, mass=mass) if mass > 0 else None
    armature = tuple(values.get("armature", ()))
    changes["armature"] = armature if any(v > 0 for v in armature) else ()
    if "load_mass" in values:
        mass = values["load_mass"]
        changes["load"] = dataclasses.replace(load or Payload(0.0), mass=mass) if mass > 0 else None
    return dataclasses.replace(system, **changes)


def one_period_rmse(system: RigidArm, logs: Sequence[RobotLog], periods: int, steps: int, seed: int = 0) -> list[float]:
    """RMSE per state of x_{k+1} predicted by RK4 (steps per period, batched over periods) from the logged x_k and
    u_k, on up to `periods` periods drawn from the logs (nan: none)."""
    x0, u, x1 = [], [], []
    for log in logs:
        inside = np.r_[log.episode[1:] == log.episode[:-1], False]
        x0.append(log.x[inside]), u.append(log.u[inside]), x1.append(log.x[np.r_[False, inside[:-1]]])
    x0, u, x1 = (np.concatenate(p) for p in (x0, u, x1))
    if periods <= 0 or not len(x0):
        return [math.nan] * (2 * system.nq)
    if len(x0) > periods:
        keep = np.random.default_rng(seed).choice(len(x0), periods, replace=False)
        x0, u, x1 = x0[keep], u[keep], x1[keep]
    with torch.no_grad():
        x = rk4_fixed(system.rhs, torch.from_numpy(x0), torch.from_numpy(u), system.tau / steps, steps)
    return _rms(x.numpy() - x1)
