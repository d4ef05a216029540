"""The Jacobian that stands in for midpoint_arm's in the controller on long arms: the arm frozen at q0 (one exact
solve over tau, as frozen_arm) with its inertia held, M(q0) a constant along q0.

midpoint_arm's exact Jacobian would cost several times its value (AD through sub-steps whose configurations depend
on every input). The frozen arm's, x_p = (q0 + v_ss tau + L d, v_ss + E d) with d = v0 - v_ss, E = exp(-M^-1 kv tau)
and L = kv^-1 M (I - E), has its v0 and u columns ([L; E], and through v_ss) from one held arm; its q0 columns add
the change of E and L with the configuration applied to d, which needs an eigendecomposition and the mass matrix's
derivatives (pinnmpc.surrogate.prior_eigen) and vanishes where the arm moves at its steady velocity (d = 0). Along a
tracked reference d stays small: the controller tracks to the printed digits with either, and the value, the
predicted trajectory and the shooting gaps stay exact (docs/design.md). E and L over tau come from the value's own
held arm over tau / steps (E_tau = E^steps, L_tau = L (I + E + ... + E^(steps - 1))), so the two share their code.
"""

from __future__ import annotations

import casadi as ca


def steady_velocity_jacobian(frozen: ca.Function, kv: ca.DM, name: str) -> ca.Function:
    """(q, u) -> (dv_ss/dq, dv_ss/du), v_ss = c0 / kv of the arm held at q (frozen: (q, u) -> (M, c0))."""
    n = frozen.size1_in(0)
    q, u = ca.SX.sym("q", n), ca.SX.sym("u", n)
    vss = frozen(q, u)[1] / kv
    return ca.Function(name, [q, u], [ca.densify(ca.jacobian(vss, q)), ca.densify(ca.jacobian(vss, u))], {"cse": True})


def held_inertia_jacobian(held_arm: ca.Function, steady: ca.Function, steps: int, tau: float, name: str) -> ca.Function:
    """(x0, u) -> J (nx (nx + nu), row-major): d x_p / d(x0, u) of the arm frozen at q0 over tau with M(q0) held.
    held_arm: (q, u) -> (v_ss, L, E) over tau / steps; steady: steady_velocity_jacobian's function. The held arm is
    called, the rest is one straight-line function of its outputs."""
    n = held_arm.size1_in(0)
    lag, e, by_q, by_u = (ca.SX.sym(a, n, n) for a in ("lag", "e", "by_q", "by_u"))
    eye = ca.SX.eye(n)
    e_tau, total = eye, ca.SX(n, n)  # E^steps and I + E + ... + E^(steps - 1), built up together
    for _ in range(steps):
        total = total + e_tau
        e_tau = ca.mtimes(e_tau, e)
    lag_tau = ca.mtimes(lag, total)
    by_vss = ca.vertcat(tau * eye - lag_tau, eye - e_tau)
    kinematic = ca.vertcat(eye, ca.SX(n, n))
    jac = ca.horzcat(kinematic + ca.mtimes(by_vss, by_q), ca.vertcat(lag_tau, e_tau), ca.mtimes(by_vss, by_u))
    assemble = ca.Function(f"{name}_assemble", [lag, e, by_q, by_u], [ca.densify(ca.vec(jac.T))], {"cse": True})
    x0, u = ca.MX.sym("x", 2 * n), ca.MX.sym("u", n)
    _, lag_h, e_h = held_arm(x0[:n], u)
    return ca.Function(name, [x0, u], [assemble(lag_h, e_h, *steady(x0[:n], u))])
