"""Classical identification: the model's physical coefficients fitted to robot logs by bounded linear least squares.

The arm's equation M(q) dv/dt + h(q, v) = torque is linear in every coefficient fitted here: per-joint viscous D and
Coulomb C (torque = u - D v - C tanh(s v)) or servo gain K and Coulomb C (torque = g0(q) + K (u - v) - C tanh(s v)),
a point mass m_p at a known place (M and h gain m_p times those of a unit mass) and per-joint armature A (on M's
diagonal). The fit integrates that equation over each fine interval of a hold period instead of differentiating the
samples: the interval's velocity change carries the inertia (A dv exactly), its position change the viscous term
(D dq exactly) and the input is held, so only the slowly varying M(q), h and the Coulomb term are averaged over the
interval's two ends.
Differences of the fine samples would not do: planar3's velocities relax within milliseconds after each input step,
below a 10 ms fine step, and the acceleration estimates were off by as much as their size. One bounded least-squares
solve (every coefficient >= 0) gives the fit, with no iterations or starting guess. A joint's equation counts only
where it moves faster than min_speed: dry friction (which sticks) has no smooth counterpart, and while sliding it is
a constant torque against the motion, which the Coulomb term C tanh(s v) then absorbs (C fitted = C + dry friction).
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
from scipy.optimize import lsq_linear

from pinnmpc.plant.integrators import rk4_fixed
from pinnmpc.robot_data.logs import RobotLog, check_enough
from pinnmpc.systems.urdf import Payload, RigidArm

KEYS = ("viscous", "coulomb", "servo_gain", "payload", "armature")  # what can be fitted


@dataclass
class Intervals:
    """Fine intervals inside hold periods: both ends' q, v (n, 2, nq), their length dt (n,) and the input u (n, nu)."""

    q: np.ndarray
    v: np.ndarray
    dt: np.ndarray
    u: np.ndarray


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


def intervals(logs: Sequence[RobotLog], max_samples: int | None = None, seed: int = 0) -> Intervals:
    """Every fine interval inside a hold period of the logs (control-rate periods where a log has no fine part),
    up to max_samples of them drawn at random."""
    parts = []
    for log in logs:
        fine = log.fine
        n = len(log.meta["input_names"])
        t, x, ep = (log.t_fine, log.x_fine, log.episode_fine) if fine > 1 else (log.t, log.x, log.episode)
        first = np.r_[True, ep[1:] != ep[:-1]]
        begin = np.maximum.accumulate(np.where(first, np.arange(len(ep)), 0))
        start = np.flatnonzero(((np.arange(len(ep)) - begin) % fine == 0) & np.r_[ep[1:] == ep[:-1], False])
        u = log.u[np.r_[log.episode[1:] == log.episode[:-1], False]]
        for a in range(fine):
            i = start + a
            ends = np.stack((x[i], x[i + 1]), axis=1)
            parts.append((ends[..., :n], ends[..., n:], t[i + 1] - t[i], u))
    q, v, dt, u = (np.concatenate(p) for p in zip(*parts))
    if max_samples is not None and len(q) > max_samples:
        keep = np.sort(np.random.default_rng(seed).choice(len(q), max_samples, replace=False))
        q, v, dt, u = q[keep], v[keep], dt[keep], u[keep]
    return Intervals(q, v, dt, u)


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


def _bare(system: RigidArm) -> RigidArm:
    """The arm without payload and armature and with unscaled friction: the fit's starting point."""
    return dataclasses.replace(system, payload=None, armature=(), friction_scale=1.0)


def regression(
    system: RigidArm, s: Intervals, fit: Sequence[str], payload: Payload
) -> tuple[np.ndarray, np.ndarray, list[str], np.ndarray]:
    """A theta = b, the equation integrated over each interval and divided by its length (torque units) for the
    coefficients named in fit (rows: interval-major, joint-minor), the column names and each row's joint;
    coefficients not fitted keep their nominal value (payload and armature: none)."""
    base = _bare(system)
    n, servo = system.nq, system.actuation == "velocity_servo"
    dq, dv, dt = s.q[:, 1] - s.q[:, 0], s.v[:, 1] - s.v[:, 0], s.dt[:, None]
    m0, h0, g0 = _interval_terms(base, s)
    rhs = (g0 if servo else s.u) - np.einsum("bij,bj->bi", m0, dv) / dt - h0  # what the fitted terms must make up
    cols: dict[str, np.ndarray] = {}
    if "payload" in fit:
        unit = dataclasses.replace(base, payload=dataclasses.replace(payload, mass=1.0))
        m1, h1, _ = _interval_terms(unit, s)
        cols["payload_mass"] = np.einsum("bij,bj->bi", m1 - m0, dv) / dt + h1 - h0
    per_joint = {
        "armature": dv / dt,
        "viscous": dq / dt,
        "coulomb": np.tanh(system.coulomb_slope * s.v).mean(1),
        "servo_gain": dq / dt - s.u,
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
    validation_periods: int = 1000,
    rk4_steps: int = 50,
    seed: int = 0,
) -> Fit:
    """Fit the named coefficients (of KEYS) to the logs; payload gives the mass's place (mass ignored; None: the
    tip, as the MuJoCo robots' convention). A joint's equation counts only where its speed exceeds min_speed at
    both ends of the interval: slower, a real arm's dry friction sticks and slips, which no smooth model follows."""
    unknown = [k for k in fit if k not in KEYS]
    if unknown:
        raise ValueError(f"fit {unknown}; expected some of {list(KEYS)}")
    friction = ("servo_gain", "coulomb") if system.actuation == "velocity_servo" else ("viscous", "coulomb")
    fit = [k for k in fit if k in (*friction, "payload", "armature")]
    if not fit:
        raise ValueError(
            f"nothing to fit for actuation {system.actuation}; expected some of {[*friction, 'payload', 'armature']}"
        )
    payload = payload or Payload(0.0)
    s = intervals(logs, max_samples, seed)
    a, b, names, joint = regression(system, s, fit, payload)
    used = (np.abs(s.v).min(axis=1) > min_speed).reshape(-1)
    check_enough(int(used.sum()) // system.nq, 20 * len(names), f"the logs (joints above min_speed={min_speed})",
                 tau=system.tau, fine=logs[0].fine, t_max=system.tau / logs[0].fine)  # fmt: skip
    weight = used / _torque_scale(system)[joint]  # each joint's equation relative to its torque range
    aw, bw = a * weight[:, None], b * weight
    scale = np.maximum(np.sqrt((aw**2).mean(axis=0)), 1e-300)
    sol = lsq_linear(aw / scale, bw, bounds=(0.0, np.inf), method="bvls", lsmr_tol="auto")
    theta = sol.x / scale
    values = _values(system, names, theta, fit)
    fitted = fitted_system(system, values, payload, name)
    mask = used.reshape(-1, system.nq)
    res, res0 = ((a @ th - b).reshape(-1, system.nq) for th in (theta, _nominal_theta(system, names)))
    pred, pred0 = (one_period_rmse(m, logs, validation_periods, rk4_steps, seed) for m in (fitted, system))
    return Fit(fitted, values, list(fit), int(used.sum()), _rms(res, mask), _rms(res0, mask), pred, pred0)


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
    return out


def fitted_system(system: RigidArm, values: dict[str, Any], payload: Payload, name: str | None = None) -> RigidArm:
    """The nominal arm with the fitted coefficients (friction scale 1, payload and armature where nonzero)."""
    changes: dict[str, Any] = {"friction_scale": 1.0, "name": name or system.name}
    for key in ("viscous", "coulomb", "servo_gain"):
        if key in values:
            changes[key] = tuple(values[key])
    mass = values.get("payload_mass", 0.0)
    changes["payload"] = dataclasses.replace(payload, mass=mass) if mass > 0 else None
    armature = tuple(values.get("armature", ()))
    changes["armature"] = armature if any(v > 0 for v in armature) else ()
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
