"""Shooting on the predicted dynamics: rollouts and the state sensitivities d x_i / d U along the horizon.

Single shooting chains the step Jacobians through a rollout (torch or numpy, plus a numpy hot path with a
receding-horizon warm start); multiple shooting linearises at lifted states in one batched call and
condenses the chain by block forward substitution. Nothing here knows the cost: HorizonOCP turns
states and sensitivities into residuals and their Jacobian.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from pinnmpc.controller.array_backend import Array, xp_of


class Predictor(Protocol):
    """What shooting needs of a horizon problem (HorizonOCP is one): its sizes and one predicted step."""

    horizon: int
    nx: int
    nu: int

    def step(self, x: Array, u: Array) -> Array:
        """One predicted step in the namespace of x."""
        ...

    def step_with_jacobian(self, x: Array, u: Array) -> tuple[Array, Array, Array]:
        """One predicted step with its Jacobians A = d y / d x and B = d y / d u."""
        ...


def rollout(model: Predictor, x0: Array, U: Array) -> Array:
    """Predicted states x_1..x_H (..., H, nx) by self-loop of the model: the cost needs them, not their slopes."""
    xs, x = [], x0
    for i in range(model.horizon):
        x = model.step(x, U[..., i, :])
        xs.append(x)
    return xp_of(x0).stack(xs, -2)


def sensitivities(model: Predictor, x0: Array, U: Array) -> tuple[Array, Array]:
    """Predicted states X (..., H, nx) and d x_i / d U (..., H, nx, H*nu), torch or numpy, by chaining the step
    Jacobians along the horizon: one path for autograd tensors and numpy alike."""
    xp = xp_of(x0)
    lead, n_var = x0.shape[:-1], model.horizon * model.nu
    sens = xp.zeros((*lead, model.nx, n_var), dtype=xp.float64)  # d x_i / d U
    xs, sens_list, x = [], [], x0
    for i in range(model.horizon):
        x, a, b = model.step_with_jacobian(x, U[..., i, :])
        sens = a @ sens
        sens[..., :, i * model.nu : (i + 1) * model.nu] += b
        xs.append(x)
        sens_list.append(sens)
    return xp.stack(xs, -2), xp.stack(sens_list, -3)


def sensitivities_numpy(
    model: Predictor, x0: np.ndarray, U: np.ndarray, prior: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Predicted states X (B, H, nx) and d x_i / d U (B, H, nx, H*nu) with preallocated arrays: the controller's
    hot path.

    prior: the sensitivities of the previous receding-horizon solve, whose plan shifted by one step
    is U. Steps 1..H-1 of the new rollout then repeat steps 2..H of the old one, so their
    sensitivities are reused (an approximation: the state moved on) and only the last step needs
    a Jacobian: about half the cost of an exact rollout.
    """
    (horizon, nx, nu), batch = (model.horizon, model.nx, model.nu), x0.shape[0]
    n_var = horizon * nu
    Ub = U.reshape(batch, horizon, nu)
    X = np.empty((batch, horizon, nx))
    sens = np.zeros((batch, horizon, nx, n_var))  # only inputs before step i act on x_i
    x = x0
    if prior is not None:
        for i in range(horizon - 1):
            x = X[:, i] = model.step(x, Ub[:, i])
        sens[:, :-1, :, :-nu] = prior[:, 1:, :, nu:]
        first = horizon - 1
    else:
        first = 0
    for i in range(first, horizon):
        x, a, b = model.step_with_jacobian(x, Ub[:, i])
        X[:, i] = x
        if i:
            np.matmul(a, sens[:, i - 1, :, : i * nu], out=sens[:, i, :, : i * nu])
        sens[:, i, :, i * nu : (i + 1) * nu] = b
    return X, sens


def linearise(
    model: Predictor, nodes: np.ndarray, U: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Multiple shooting: one batched network call at all nodes (B, H, nx), then the linearised predictions
    x_1..x_H (B, H, nx), their sensitivities to U (B, H*nx, H*nu), the largest defect per problem and the
    step Jacobians A_i (B, H, nx, nx) that chain them; H steps in one call instead of H sequential ones.

    The chain x_i = y_i + A_i (x_{i-1} - s_i) over the horizon is solved for the predictions and all H*nu
    input directions at once (chain_solve).
    """
    batch, horizon, nx = nodes.shape
    nu = model.nu
    y, a, b = model.step_with_jacobian(nodes, U.reshape(batch, horizon, nu))
    rhs = np.zeros((batch, horizon, nx, horizon * nu + 1))
    blocks = rhs[..., :-1].reshape(batch, horizon, nx, horizon, nu)
    diag = np.arange(horizon)
    blocks[:, diag, :, diag, :] = b.swapaxes(0, 1)  # x_i depends directly on u_i only through B_i
    rhs[..., -1] = y
    rhs[:, 1:, :, -1] -= (a[:, 1:] @ nodes[:, 1:, :, None])[..., 0]
    sol = chain_solve(a, rhs).reshape(batch, horizon * nx, -1)
    defect = np.abs(y[:, :-1] - nodes[:, 1:]).reshape(batch, -1).max(-1, initial=0.0)
    return sol[..., -1].reshape(batch, horizon, nx), sol[..., :-1], defect, a


def reached(
    model: Predictor, x0: np.ndarray, nodes: np.ndarray, U: np.ndarray, a: np.ndarray, tol_final_defect: float
) -> np.ndarray:
    """The states U reaches from x0 (B, H, nx) without a sequential rollout where the lifted states have converged.

    One batched network call at the final nodes, their defects carried through the last linearisation's step
    Jacobians a (x_i - y_i = A_i (x_{i-1} - y_{i-1} + gap_{i-1}), exact to second order in the defects, which are
    tiny at convergence); a full rollout where one is larger than tol_final_defect.
    """
    batch, horizon, nx = nodes.shape
    y = model.step(nodes, U)
    gap = np.zeros((batch, horizon, nx))  # gap_i = F(s_i, u_i) - s_{i+1}: the defect at the end of step i
    gap[:, :-1] = y[:, :-1] - nodes[:, 1:]
    X = y + chain_solve(a, gap[..., None])[..., 0] - gap
    far = np.flatnonzero(np.abs(gap).reshape(batch, -1).max(-1) > tol_final_defect)
    if far.size:
        X[far] = rollout(model, x0[far], U[far])
    return X


def chain_solve(a: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """x (B, H, nx, k) with x_0 = r_0, x_i = r_i + A_i x_{i-1}: the linearised chain of multiple shooting
    ((I - L) x = r, L holding A_1..A_{H-1} on the block subdiagonal) by forward substitution, H small products
    instead of a dense (H nx)^2 solve."""
    out = np.empty_like(rhs)
    out[:, 0] = rhs[:, 0]
    for i in range(1, rhs.shape[1]):
        np.matmul(a[:, i], out[:, i - 1], out=out[:, i])
        out[:, i] += rhs[:, i]
    return out
