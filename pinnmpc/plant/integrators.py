"""Fixed-step integrators over one zero-hold period: baselines and accurate reference solutions.

Written once over plain arithmetic, so the same code integrates torch tensors (differentiable), numpy arrays
and CasADi symbols (the compiled true-model step of pinnmpc.surrogate.flowmap)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

Array = Any  # torch Tensor, numpy array or CasADi symbol: anything with + and scalar *
Rhs = Callable[[Array, Array], Array]


def n_steps(tau: float, h: float) -> int:
    """Whole number of steps that cover tau with steps no longer than h."""
    if tau <= 0 or h <= 0:
        raise ValueError(f"tau and h must be positive, got tau={tau}, h={h}")
    return max(1, round(tau / h)) if abs(tau / h - round(tau / h)) < 1e-9 else int(tau // h) + 1


def euler_step(rhs: Rhs, x0: Array, u: Array, tau: float, h: float) -> Array:
    """Explicit Euler over tau with zero-hold u (the paper's cheapest baseline)."""
    n = n_steps(tau, h)
    dt = tau / n
    x = x0
    for _ in range(n):
        x = x + dt * rhs(x, u)
    return x


def rk4_step(rhs: Rhs, x0: Array, u: Array, tau: float, h: float) -> Array:
    """Classical RK4 over tau with zero-hold u; h = tau/10 is the paper's baseline."""
    n = n_steps(tau, h)
    return rk4_fixed(rhs, x0, u, tau / n, n)


def rk4_fixed(rhs: Rhs, x0: Array, u: Array, dt: Array, n: int) -> Array:
    """n classical RK4 steps of length dt, a scalar or one per row (an (N, 1) array: every row to its own time)."""
    x = x0
    for _ in range(n):
        k1 = rhs(x, u)
        k2 = rhs(x + 0.5 * dt * k1, u)
        k3 = rhs(x + 0.5 * dt * k2, u)
        k4 = rhs(x + dt * k3, u)
        x = x + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
    return x
