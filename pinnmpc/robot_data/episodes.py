"""Logs in use: the one-period transitions a fine-tuning fits and validates on, and episodes held out or kept."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import numpy as np
import torch
from torch import Tensor

from pinnmpc.robot_data.logs import TIME_TOL, RobotLog, first_index, period_starts


def input_steps(log: RobotLog) -> np.ndarray:
    """Per control-rate sample, the largest change of any input from the episode's previous period (0 for an
    episode's first): how far the robot's command moved as the period began."""
    step = np.r_[0.0, np.abs(np.diff(log.u, axis=0)).max(axis=1)] if len(log.u) else np.zeros(0)
    return np.where(np.r_[False, log.episode[1:] == log.episode[:-1]], step, 0.0)


def previous_inputs(log: RobotLog) -> np.ndarray:
    """Per control-rate sample, the input of the episode's period before (an episode's first: its own, as a lag that
    starts settled)."""
    before = np.r_[False, log.episode[1:] == log.episode[:-1]] if len(log.u) else np.zeros(0, dtype=bool)
    return np.where(before[:, None], np.roll(log.u, 1, axis=0), log.u)


def transitions(
    logs: Sequence[RobotLog],
    t_max: float,
    max_input_step: float | None = None,
    previous_input: bool = False,
    start_at: float | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Every pair i < j of samples (fine where present) within one hold period of one episode with
    t = t_j - t_i <= t_max: float64 tensors t (n, 1), x0 (n, nx), u (n, nu), x_t (n, nx); with max_input_step,
    only periods whose input moved at most that far from the previous period's (input_steps). previous_input: u is
    (u, u_prev) (n, 2 nu) and only pairs from a period's start count (within it, what the actuator still carries of
    u_prev is unknown). start_at: only pairs from the sample that far (s, on the fine samples) into the period (a
    network split at model.command_delay: x(t) from there under the period's own input)."""
    parts = []
    for log in logs:
        fine = log.fine
        skip = 0 if start_at is None else round(start_at / (log.tau / fine))
        if start_at is not None and (abs(skip * log.tau / fine - start_at) > TIME_TOL * log.tau / fine or skip >= fine):
            raise ValueError(
                f"pairs from {start_at:g} s into each period (model.command_delay) on a log with fine samples every "
                f"{log.tau / fine:g} s; expected a multiple of that below the period"
            )
        tt, xx, ee = (log.t_fine, log.x_fine, log.episode_fine) if fine > 1 else (log.t, log.x, log.episode)
        first = first_index(ee)
        start = np.flatnonzero(((np.arange(len(tt)) - first) % fine == 0) & period_starts(ee))  # fine index per period
        periods = period_starts(log.episode)
        u = log.u[periods]  # the same periods, in the same order
        if previous_input:
            u = np.concatenate((u, previous_inputs(log)[periods]), axis=1)
        calm = np.ones(len(u), dtype=bool) if max_input_step is None else input_steps(log)[periods] <= max_input_step
        tol = TIME_TOL * log.tau / fine
        one = previous_input or start_at is not None  # pairs from one sample of the period only
        for a in range(skip, skip + 1 if one else fine):  # the pair's first sample within the period
            for b in range(a + 1, fine + 1):
                i, j = start + a, start + b
                dt = tt[j] - tt[i]
                keep = (dt <= t_max + tol) & calm
                if keep.any():
                    parts.append((dt[keep], xx[i[keep]], u[keep], xx[j[keep]]))
    if not parts:
        nx = len(logs[0].meta["state_names"]) if logs else 0
        nu = len(logs[0].meta["input_names"]) * (2 if previous_input else 1) if logs else 0
        empty = [torch.zeros(0, k, dtype=torch.float64) for k in (1, nx, nu, nx)]
        return empty[0], empty[1], empty[2], empty[3]
    t, x0, u, xt = (np.concatenate(p) for p in zip(*parts))
    return tuple(torch.from_numpy(np.ascontiguousarray(a)) for a in (t[:, None], x0, u, xt))  # type: ignore[return-value]


def transitions_per_second(tau: float, fine: int, t_max: float, from_start: bool = False) -> float:
    """How many transitions one second of robot time gives (pairs per period over tau; from_start: only those from
    the period's start, as with the previous input)."""
    h = tau / fine
    d = min(fine, int(math.floor(t_max / h + TIME_TOL)))
    return (d if from_start else sum(fine + 1 - k for k in range(1, d + 1))) / tau


def check_enough(
    n_transitions: int,
    need: int,
    what: str,
    *,
    tau: float | None = None,
    fine: int = 1,
    t_max: float | None = None,
    from_start: bool = False,
) -> None:
    """Too little data is refused in one line saying how much is needed (in robot time, with tau and t_max)."""
    if n_transitions >= need:
        return
    hint = ""
    if tau is not None:
        rate = transitions_per_second(tau, fine, tau if t_max is None else t_max, from_start)
        if rate > 0:
            hint = f" (about {need / rate:.3g} s of robot time at tau={tau:g} with fine={fine})"
    raise ValueError(f"{what} hold {n_transitions} transitions; expected at least {need}{hint}")


def select_episodes(log: RobotLog, ids: Sequence[int]) -> RobotLog:
    """The log restricted to some episodes (meta kept)."""
    ids = np.asarray(list(ids), dtype=np.int64)
    keep = np.isin(log.episode, ids)
    out = replace(log, t=log.t[keep], x=log.x[keep], u=log.u[keep], episode=log.episode[keep], meta=dict(log.meta))
    if log.t_fine is not None:
        kf = np.isin(log.episode_fine, ids)
        out = replace(out, t_fine=log.t_fine[kf], x_fine=log.x_fine[kf], episode_fine=log.episode_fine[kf])
        if log.command_fine is not None:
            out = replace(out, command_fine=log.command_fine[kf])
    return out


def split_episodes(log: RobotLog, fraction: float, seed: int = 0) -> tuple[RobotLog, RobotLog]:
    """(train, validation): whole episodes held out, round(fraction * episodes) of them drawn at random (at least one
    when fraction > 0 and the log has two or more), so no validation pair shares an episode with training."""
    if not 0.0 <= fraction < 1.0:
        raise ValueError(f"validation fraction={fraction!r}; expected a number in [0, 1)")
    ids = log.episodes
    k = 0 if fraction == 0 or len(ids) < 2 else min(len(ids) - 1, max(1, round(fraction * len(ids))))
    held = np.random.default_rng(seed).choice(ids, size=k, replace=False) if k else np.zeros(0, dtype=np.int64)
    return select_episodes(log, [i for i in ids if i not in set(held.tolist())]), select_episodes(log, held)
