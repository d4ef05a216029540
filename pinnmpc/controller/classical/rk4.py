"""RK4 shooting for the classical NMPC: the sub-steps that are stable on the state box, and the flow over a period
with its sensitivities."""

from __future__ import annotations

import math
from typing import Any

import casadi as ca
import numpy as np

from pinnmpc.plant.integrators import rk4_fixed

RK4_STABLE = 2.0  # h * max|eig(df/dx)| kept below this (RK4's real stability bound is 2.785)
STIFFNESS_SAMPLES = 400  # states sampled to estimate the stiffest eigenvalue


def stable_rk4_steps(
    system: Any, tau: float, seed: int = 0, rhs: ca.Function | None = None, at_rest: bool = False
) -> int:
    """Fewest RK4 sub-steps per tau that keep h * max|eig(df/dx)| below RK4_STABLE on the state box (of rhs, by
    default the system's).

    Friction with a steep tanh makes the arms stiff near zero velocity, so half the samples there; with at_rest a
    quarter at exactly zero, where a smoothed sign(v) (tanh(v / width), any width) is steepest."""
    rhs = system.casadi_rhs() if rhs is None else rhs
    nx, nu = rhs.size1_in(0), rhs.size1_in(1)
    x, u = ca.SX.sym("x", nx), ca.SX.sym("u", nu)
    jac = ca.Function("rhs_jacobian", [x, u], [ca.jacobian(rhs(x, u), x)]).map(STIFFNESS_SAMPLES)
    rng = np.random.default_rng(seed)
    lo, hi = np.array(system.state_box.low), np.array(system.state_box.high)
    xs = rng.uniform(lo, hi, (STIFFNESS_SAMPLES, nx))
    xs[::2, nx // 2 :] *= 1e-3  # velocities near zero: the steepest friction slope
    if at_rest:
        xs[::4, nx // 2 :] = 0.0
    us = rng.uniform(system.input_box.low, system.input_box.high, (STIFFNESS_SAMPLES, nu))
    jacs = np.asarray(jac(xs.T, us.T)).reshape(nx, STIFFNESS_SAMPLES, nx).transpose(1, 0, 2)
    worst = float(np.abs(np.linalg.eigvals(jacs)).max())
    return max(1, math.ceil(tau * worst / RK4_STABLE))


def rk4_flow(rhs: ca.Function, tau: float, steps: int) -> tuple[ca.Function, ca.Function]:
    """F(x, u): the zero-order-hold flow over tau by `steps` RK4 steps, a loop (mapaccum) of one SX step, and
    F_sens(x, u) = (F, dF/dx, dF/du) by forward sensitivities carried through the same loop (one SX step with
    its own Jacobian, cheaper than AD through the loop)."""
    nx, nu = rhs.size1_in(0), rhs.size1_in(1)
    h = tau / steps
    x, u, s = ca.SX.sym("x", nx), ca.SX.sym("u", nu), ca.SX.sym("s", nx, nx + nu)
    nxt = rk4_fixed(rhs, x, u, h, 1)  # one step on symbols: the same RK4 as every other path
    step = ca.Function("rk4_step", [x, u], [nxt], {"cse": True})
    s_next = ca.jacobian(nxt, x) @ s + ca.horzcat(ca.SX.zeros(nx, nx), ca.jacobian(nxt, u))
    sens = ca.Function("rk4_sens", [x, u, s], [nxt, s_next], {"cse": True})
    xm, um = ca.MX.sym("x", nx), ca.MX.sym("u", nu)
    xs = step.mapaccum("rk4_loop", steps)(xm, ca.repmat(um, 1, steps))
    flow = ca.Function("F", [xm, um], [xs[:, -1]], ["x", "u"], ["xf"])
    s0 = ca.horzcat(ca.MX.eye(nx), ca.MX.zeros(nx, nu))
    xs, ss = sens.mapaccum("rk4_sens_loop", steps, [0, 2], [0, 1])(xm, ca.repmat(um, 1, steps), s0)
    last = ss[:, -(nx + nu) :]
    outs = [xs[:, -1], last[:, :nx], last[:, nx:]]
    return flow, ca.Function("F_sens", [xm, um], outs, ["x", "u"], ["xf", "A", "B"])
