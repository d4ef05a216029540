"""Built-in references of kind `driven`: what the true arm does when a loose feedback drives it around a random path.

The path kinds (waypoints, sine, random) are drawn by hand to stay within reach. A driven reference is a motion of
the true model under inputs inside the input box, so a controller with a perfect model could track it exactly, and
nothing in it was shaped to suit a network. The feedback needs only the system's rhs (any system whose acceleration
is affine in u, a = a0(x) + B(x) u, with one input per joint):

    u = clip(B^-1 (w^2 (q_d - q) + 2 zeta w (v_d - v) - a0))

so, while the input box does not clip it, the arm lags the path like a damped second-order filter of bandwidth w;
where it clips, the true dynamics take over. The motion is the true ODE's, integrated tightly.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.integrate import solve_ivp

from pinnmpc.util.checks import positive

RTOL = ATOL = 1e-9  # solve_ivp tolerances of the driven motion: far below any tracking error a reference is used for


def _affine_input(system: Any, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """a0 = acceleration at input 0 and B = da/du at state x (exact for a rhs affine in u), from nq + 1 rhs calls."""
    nq = len(x) // 2
    us = np.vstack([np.zeros(nq), np.eye(nq)])
    acc = np.asarray(system.rhs(np.broadcast_to(x, (nq + 1, len(x))).copy(), us))[:, nq:]
    return acc[0], (acc[1:] - acc[0]).T


def drive(
    system: Any,
    path: Any,
    duration: float,
    times: np.ndarray,
    bandwidth: float,
    damping: float,
) -> np.ndarray:
    """States of the true system at `times`, driven from rest at the path's start along path(t) -> (q_d, v_d)."""
    nq = system.nq
    if len(system.input_names) != nq:
        raise ValueError(
            f"a driven reference needs one input per joint; {system.name} has {len(system.input_names)} inputs for "
            f"{nq} joints"
        )
    low, high = (np.asarray(b, dtype=np.float64) for b in (system.input_box.low, system.input_box.high))
    q_start, _ = path(0.0)

    def closed_loop(t: float, x: np.ndarray) -> np.ndarray:
        """dx/dt of the true system under the feedback."""
        q_d, v_d = path(t)
        a0, b = _affine_input(system, x)
        command = bandwidth**2 * (q_d - x[:nq]) + 2.0 * damping * bandwidth * (v_d - x[nq:])
        u = np.clip(np.linalg.solve(b, command - a0), low, high)
        return np.concatenate([x[nq:], a0 + b @ u])  # the rhs at u, from the terms already evaluated

    x0 = np.concatenate([q_start, np.zeros(nq)])
    sol = solve_ivp(closed_loop, (0.0, duration), x0, method="RK45", t_eval=times, rtol=RTOL, atol=ATOL)
    if not sol.success:
        raise RuntimeError(f"the driven reference's integration failed: {sol.message}")
    return sol.y.T


def check_gains(name: str, bandwidth: object, damping: object) -> tuple[float, float]:
    """bandwidth (rad/s) and damping as positive finite numbers, or a one-line error naming the reference."""
    for key, value in (("bandwidth", bandwidth), ("damping", damping)):
        bad = positive()(value, {})
        if bad is not None:
            raise ValueError(f"built-in reference {name!r}: {key}={value!r}; expected {bad}")
    return float(bandwidth), float(damping)  # type: ignore[arg-type]
