"""The horizon optimal control problem as a batched nonlinear least-squares problem on a flow map.

The problem: weights, cost, residuals, joint limits, and the one Jacobian path that turns the state
sensitivities of pinnmpc.controller.shooting into the residuals' Jacobian (the box-constrained step is in
pinnmpc.controller.box_step). Everything here works on torch tensors (autograd, for the torch.optim
solvers) and on numpy arrays (the fast Gauss-Newton path), with the same formulas. The model is any
pinnmpc.surrogate.flowmap.FlowMap: the surrogate, its numpy fast path or the true model by RK4.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from types import ModuleType
from typing import Any

import numpy as np
import torch
from torch import Tensor

from pinnmpc.controller import shooting
from pinnmpc.controller.array_backend import Array, cat, xp_of
from pinnmpc.controller.limits import LIMIT_KEYS, JointLimits, as_float
from pinnmpc.surrogate.flowmap import FlowMap, check_flow_map, numpy_path, passes_plain_rows

Deferred = tuple[np.ndarray, np.ndarray, Callable[[np.ndarray], Any]]  # x_prev, u_prev, update: defer_estimate's

__all__ = ["LIMIT_KEYS", "Array", "HorizonOCP", "JointLimits", "cat", "psd_sqrt", "xp_of"]  # JointLimits: limits.py


def psd_sqrt(matrix: Sequence[Sequence[float]] | Sequence[float], n: int, name: str) -> Tensor:
    """Symmetric square root W of a PSD weight (W^T W = matrix); a flat list is a diagonal."""
    try:
        m = torch.as_tensor(matrix, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        raise ValueError(f"{name}={matrix!r}; expected {n} diagonal entries or an {n}x{n} matrix of numbers") from None
    if m.ndim == 1:
        m = torch.diag(m)
    if m.shape != (n, n):
        raise ValueError(f"{name} must be {n} diagonal entries or an {n}x{n} matrix, got shape {tuple(m.shape)}")
    if not torch.all(torch.isfinite(m)):
        raise ValueError(f"{name} has non-finite entries: {m.tolist()}")
    if not torch.allclose(m, m.T, rtol=0.0, atol=1e-12):
        raise ValueError(f"{name} must be symmetric, got {m.tolist()}")
    eig, vec = torch.linalg.eigh(m)
    if eig.min() < -1e-12 * max(1.0, float(eig.abs().max())):
        raise ValueError(f"{name} must be positive semidefinite; its smallest eigenvalue is {float(eig.min()):.3g}")
    return vec @ torch.diag(eig.clamp_min(0).sqrt()) @ vec.T


class HorizonOCP:
    """min_U sum_i ||W_q (x_i - x_ref_i)||^2 + ||W_r u_i||^2 + ||W_d (u_i - u_{i-1})||^2 (+ the joint-limit
    penalty of JointLimits on every x_i), x_{i+1} = F.step(x_i, u_i)."""

    def __init__(
        self,
        model: FlowMap,
        horizon: int,
        Q: Sequence,
        R: Sequence,
        R_rate: Sequence | None = None,
        joint_limits: JointLimits | Mapping | None = None,
    ) -> None:
        if isinstance(horizon, bool) or not isinstance(horizon, (int, np.integer)) or horizon < 1:
            raise ValueError(f"horizon={horizon!r}; expected a whole number >= 1")
        check_flow_map(model)
        self.model = model
        self.horizon = int(horizon)
        nx, nu = model.nx, model.nu
        self.nx, self.nu = nx, nu
        w_d = None if R_rate is None else psd_sqrt(R_rate, nu, "R_rate")
        if w_d is not None and not torch.any(w_d != 0):
            w_d = None
        self.weights = {torch: (psd_sqrt(Q, nx, "Q"), psd_sqrt(R, nu, "R"), w_d)}
        self.weights[np] = tuple(None if w is None else w.numpy() for w in self.weights[torch])
        w_q = self.weights[np][0]
        self._state_rows = w_q[np.abs(w_q).sum(-1) > 0]  # sqrt(Q)'s nonzero rows: the residuals the Gauss-Newton
        #   model forms (a zero row, such as an unweighted velocity's, adds nothing to the cost, J^T J or the gradient)
        self.nq = int(getattr(model, "nq", nx // 2))  # joints: the first 2 nq states are (q, v); more follow on a
        #   model that carries the previous input (pinnmpc.surrogate.previous_input)
        self.joint_limits = JointLimits.from_config(joint_limits, self.nq)
        self._limits: dict[ModuleType, tuple] | None = None  # per namespace: joints, where penalties start, sqrt(w)
        if self.joint_limits is not None and self.joint_limits.joints.size:
            joints, (lo, hi) = self.joint_limits.joints, self.joint_limits.inner
            scale = math.sqrt(self.joint_limits.weight)
            self._limits = {  # torch's copies: the limits' arrays are read-only
                np: (joints, lo, hi, scale),
                torch: (torch.tensor(joints), torch.tensor(lo), torch.tensor(hi), scale),
            }
        self._jac_u: dict[ModuleType, Array] = {}
        self._normal_u: tuple[np.ndarray, np.ndarray] | None = None
        self.differentiable = getattr(model, "array_api", "torch") == "torch"  # torch calls keep autograd
        fast = numpy_path(model) or (None if self.differentiable else model)
        self.flow: FlowMap | None = fast  # the numpy fast path (None: numpy arrays go through torch)
        self._pending: Deferred | None = None  # an offset-free estimate waiting for its model step (defer_estimate)
        self.disturbance = None

    @property
    def surrogate(self) -> FlowMap:
        """The model predicted with (the name from when it was always the surrogate)."""
        return self.model

    @property
    def w_q(self) -> Tensor:
        """Square root of Q (torch)."""
        return self.weights[torch][0]

    @property
    def w_r(self) -> Tensor:
        """Square root of R (torch)."""
        return self.weights[torch][1]

    @property
    def w_d(self) -> Tensor | None:
        """Square root of R_rate (torch), None when the rate penalty is off."""
        return self.weights[torch][2]

    @property
    def has_rate(self) -> bool:
        """Whether the input-rate penalty is on."""
        return self.weights[np][2] is not None

    @property
    def n_limits(self) -> int:
        """Joints with a soft position limit (0: none)."""
        return 0 if self._limits is None else self.joint_limits.joints.size

    @property
    def n_residuals(self) -> int:
        """Length of the stacked residual vector per problem: states, inputs (and rates), joint limits."""
        return self.horizon * (self.nx + self.nu + (self.nu if self.has_rate else 0) + self.n_limits)

    @property
    def disturbance(self) -> np.ndarray | None:
        """Additive disturbance d (nx,) on every predicted step, x_{i+1} = F(x_i, u_i) + d (None: none)."""
        if self._pending is not None:
            self.settle()
        return self._disturbance

    @disturbance.setter
    def disturbance(self, d: np.ndarray | Sequence[float] | None) -> None:
        """Set d, e.g. the last one-step prediction error (offset-free MPC)."""
        if d is not None:
            d = np.array(d, dtype=np.float64)
            if d.shape != (self.nx,) or not np.isfinite(d).all():
                raise ValueError(f"disturbance must be {self.nx} finite numbers (one per state), got {d.tolist()}")
        self.estimated(d)

    def estimated(self, d: np.ndarray | None) -> None:
        """Set d to the offset-free estimator's value (OffsetFree.update): finite, one per state and a new array each
        update by construction, so it is kept as it is, not copied and checked as the public setter does. An estimate
        still deferred is dropped."""
        self._pending = None
        self._disturbance = d
        self._disturbance_torch: Tensor | None = None  # its tensor view, made when a torch solver first adds it

    def defer_estimate(self, x_prev: np.ndarray, u_prev: np.ndarray, update: Callable[[np.ndarray], Any]) -> None:
        """The offset-free estimate from the undisturbed step F(x_prev, u_prev), made where the model is next used:
        update(F) gives the d to predict with. A numpy flow with step_with_jacobian_plus evaluates that step in the
        pass over the horizon's nodes; any other use of d settles it first by a step of its own."""
        self._pending = (x_prev, u_prev, update)

    def settle(self) -> None:
        """Make a deferred estimate now, by its own model step (nothing where none waits)."""
        pending, self._pending = self._pending, None
        if pending is not None:
            x_prev, u_prev, update = pending
            self.estimated(update(self._model_step(x_prev, u_prev)))

    def _disturbed(self, x: Array) -> Array:
        """x + d where a disturbance is set."""
        if self._pending is not None:
            self.settle()
        d = self._disturbance
        if d is None:
            return x
        if isinstance(x, Tensor):
            if self._disturbance_torch is None:
                self._disturbance_torch = torch.from_numpy(d)
            return x + self._disturbance_torch
        return x + d

    def _numpy_only(self, *arrays: Tensor) -> list[np.ndarray]:
        """Tensors for a numpy-only model: fine as constants, an error where autograd must pass through."""
        if any(a.requires_grad for a in arrays):
            raise TypeError(
                f"{type(self.model).__name__} works on numpy arrays only; solvers that differentiate through "
                "torch (rmsprop, lbfgs, autograd gradients) need a torch flow map such as the Surrogate"
            )
        return [a.detach().numpy() for a in arrays]

    def _model_step(self, x: Array, u: Array) -> Array:
        """One undisturbed model step in the namespace of x."""
        if isinstance(x, Tensor):
            if self.differentiable:
                return self.model.step(x, u)
            return torch.from_numpy(self.flow.step(*self._numpy_only(x, u)))
        if self.flow is not None:
            return self.flow.step(x, u)
        return self.model.step(torch.from_numpy(x), torch.from_numpy(u)).numpy()

    def step(self, x: Array, u: Array) -> Array:
        """One predicted step (model plus disturbance) in the namespace of x."""
        return self._disturbed(self._model_step(x, u))

    def step_with_jacobian(self, x: Array, u: Array) -> tuple[Array, Array, Array]:
        """One predicted step with its Jacobians (d is constant), in the namespace of x."""
        if isinstance(x, Tensor) and self.differentiable:
            y, a, b = self.model.step_with_jacobian(x, u)
        elif isinstance(x, Tensor):
            y, a, b = (torch.from_numpy(v) for v in self.flow.step_with_jacobian(*self._numpy_only(x, u)))
        elif self.flow is not None:
            pending = self._pending
            if pending is None or not passes_plain_rows(self.flow):
                y, a, b = self.flow.step_with_jacobian(x, u)
            else:  # the deferred estimate's step rides with the nodes
                x_prev, u_prev, update = pending
                y, a, b, nxt = self.flow.step_with_jacobian_plus(x, u, x_prev[None], u_prev[None])
                self.estimated(update(nxt[0]))
        else:
            t = self.model.step_with_jacobian(torch.from_numpy(x), torch.from_numpy(u))
            y, a, b = (v.numpy() for v in t)
        return self._disturbed(y), a, b

    def step_with_input_jacobian(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One predicted step and B = dx/du alone (numpy): the flow's own cheaper path where its class has one
        (a wrapper's forwarded attribute would be its inner map's), else step_with_jacobian's."""
        if self.flow is None or getattr(type(self.flow), "step_with_input_jacobian", None) is None:
            y, _, b = self.step_with_jacobian(x, u)
            return y, b
        y, b = self.flow.step_with_input_jacobian(x, u)
        return self._disturbed(y), b

    def prediction_error(self, x_prev: np.ndarray, u_prev: np.ndarray, x: np.ndarray) -> np.ndarray:
        """What the undisturbed model missed over the last period: x - F(x_prev, u_prev)."""
        return x - self._model_step(x_prev, u_prev)

    def rollout(self, x0: Array, U: Array) -> Array:
        """Predicted states x_1..x_H (..., H, nx) by self-loop of the model."""
        return shooting.rollout(self, x0, U)

    def residuals(self, X: Array, U: Array, x_ref: Array, u_prev: Array) -> Array:
        """Stacked weighted residuals (..., m): states, inputs (and rates), joint limits; the cost is their squared
        norm."""
        w_q = self.weights[xp_of(U)][0]
        lead = U.shape[:-2]
        parts = [((X - x_ref) @ w_q.T).reshape(*lead, -1), self.input_residuals(U, u_prev)]
        if self._limits is not None:
            parts.append(self.limit_residuals(X).reshape(*lead, -1))
        return cat(parts, -1)

    def limit_residuals(self, X: Array) -> Array:
        """The joint-limit residuals (..., H, n_limits) of predicted states X (..., H, nx): sqrt(w) times how far
        each limited position lies beyond [low + margin, high - margin] (see JointLimits)."""
        joints, lo, hi, scale = self._limits[xp_of(X)]
        ahead_low, ahead_high = self.joint_limits.ahead(X)  # the positions themselves without a lookahead
        if isinstance(X, np.ndarray):  # ufuncs: ndarray.clip's Python wrapper costs more than the arithmetic here
            return scale * (np.maximum(ahead_high - hi, 0.0) + np.minimum(ahead_low - lo, 0.0))
        return scale * ((ahead_high - hi).clip(min=0.0) + (ahead_low - lo).clip(max=0.0))

    def limit_jacobian(self, X: Array, sens: Array) -> Array:
        """d(limit residuals)/dU (..., H*n_limits, H*nu) from predicted states X (..., H, nx) and their sensitivities
        sens (..., H, nx, H*nu): sqrt(w) times the position's sensitivity where a penalty is active, else zero."""
        joints, lo, hi, scale = self._limits[xp_of(X)]
        ahead_low, ahead_high = self.joint_limits.ahead(X)
        below, above = ahead_low < lo, ahead_high > hi
        rows = as_float(below | above, scale)[..., None] * sens[..., joints, :]
        if self.joint_limits.lookahead:  # the velocity counts where the joint moves towards the limit it is past
            velocities = self.nq + joints
            v = X[..., velocities]
            moving = (below & (v < 0)) | (above & (v > 0))
            gain = as_float(moving, scale * self.joint_limits.lookahead)
            rows = rows + gain[..., None] * sens[..., velocities, :]
        return rows.reshape(*rows.shape[:-3], -1, rows.shape[-1])

    def input_residuals(self, U: Array, u_prev: Array) -> Array:
        """The input (and input-rate) part of the residuals (..., m_u): linear in U, no model involved."""
        _, w_r, w_d = self.weights[xp_of(U)]
        lead = U.shape[:-2]
        parts = [(U @ w_r.T).reshape(*lead, -1)]
        if w_d is not None:
            du = U - cat([u_prev[..., None, :], U[..., :-1, :]], -2)
            parts.append((du @ w_d.T).reshape(*lead, -1))
        return cat(parts, -1)

    def gauss_newton_model(
        self, X: np.ndarray, sens: np.ndarray, U: np.ndarray, x_ref: np.ndarray, u_prev: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cost (B,), J^T J (B, n, n) and gradient (B, n) at predicted states X (B, H, nx) with sensitivities
        d X / d U (B, H*nx, n), numpy, without forming J: its input part is constant, so is its J^T J."""
        batch, (horizon, nx, nu) = X.shape[0], (self.horizon, self.nx, self.nu)
        w_q = self._state_rows
        U3 = U.reshape(batch, horizon, nu)
        rx = ((X.reshape(batch, horizon, nx) - x_ref) @ w_q.T).reshape(batch, -1)
        ru = self.input_residuals(U3, u_prev.reshape(batch, nu))
        sq = (w_q @ sens.reshape(batch, horizon, nx, -1)).reshape(batch, horizon * len(w_q), -1)
        st = sq.swapaxes(-1, -2)
        jac_u, jtj_u = self._input_normal()
        jtj = st @ sq
        jtj += jtj_u
        grad = (st @ rx[..., None])[..., 0]
        grad += ru @ jac_u
        cost = np.einsum("bm,bm->b", rx, rx) + np.einsum("bm,bm->b", ru, ru)
        if self._limits is not None:
            X3 = X.reshape(batch, horizon, nx)
            rl = self.limit_residuals(X3).reshape(batch, -1)
            if rl.any():  # a penalty is active somewhere (else its residuals and Jacobian rows are all zero)
                jl = self.limit_jacobian(X3, sens.reshape(batch, horizon, nx, -1))
                jtj += jl.swapaxes(-1, -2) @ jl
                grad += (rl[:, None, :] @ jl)[:, 0]
                cost = cost + np.einsum("bm,bm->b", rl, rl)
        grad *= 2.0
        return cost, jtj, grad

    def _input_normal(self) -> tuple[np.ndarray, np.ndarray]:
        """The constant input Jacobian and its J^T J (numpy), computed once."""
        if self._normal_u is None:
            jac_u = self._input_jacobian(np)
            self._normal_u = (jac_u, jac_u.T @ jac_u)
        return self._normal_u

    def cost(self, x0: Array, U: Array, x_ref: Array, u_prev: Array) -> Array:
        """Horizon cost per problem (...,)."""
        return (self.residuals(self.rollout(x0, U), U, x_ref, u_prev) ** 2).sum(-1)

    def residuals_and_jacobian(self, x0: Array, U: Array, x_ref: Array, u_prev: Array) -> tuple[Array, Array]:
        """Residuals (..., m) and their Jacobian (..., m, H*nu) from step Jacobians chained along the horizon."""
        if self.flow is not None and isinstance(x0, np.ndarray):
            return self._residuals_and_jacobian_numpy(x0, U, x_ref, u_prev)
        xp = xp_of(x0)
        w_q = self.weights[xp][0]
        lead, n_var = x0.shape[:-1], self.horizon * self.nu
        X, S = shooting.sensitivities(self, x0, U)  # d x_i / d U
        r = self.residuals(X, U, x_ref, u_prev)
        jac_x = (w_q @ S).reshape(*lead, self.horizon * self.nx, n_var)
        jac_u = self._input_jacobian(xp)  # constant: the input and input-rate residuals are linear in U
        parts = [jac_x, xp.broadcast_to(jac_u, (*lead, *jac_u.shape))]
        if self._limits is not None:
            parts.append(self.limit_jacobian(X, S))
        return r, cat(parts, -2)

    def _residuals_and_jacobian_numpy(
        self, x0: np.ndarray, U: np.ndarray, x_ref: np.ndarray, u_prev: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The same with preallocated arrays and no namespace dispatch: the controller's hot path."""
        lead = x0.shape[:-1]
        r, jac, _ = self.jacobian_rollout(x0.reshape(-1, self.nx), U, x_ref, u_prev)
        return r.reshape(*lead, -1), jac.reshape(*lead, *jac.shape[1:])

    def jacobian_rollout(
        self, x0: np.ndarray, U: np.ndarray, x_ref: np.ndarray, u_prev: np.ndarray, prior: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Residuals (B, m), Jacobian (B, m, H*nu) and state sensitivities d x_i / d U (B, H, nx, H*nu), numpy.

        prior: the sensitivities of the previous receding-horizon solve, whose plan shifted by one step
        is U: see shooting.sensitivities_numpy.
        """
        X, sens = shooting.sensitivities_numpy(self, x0, U, prior)
        r, jac = self.least_squares(X, sens, U, x_ref, u_prev)
        return r, jac, sens

    def least_squares(
        self, X: np.ndarray, sens: np.ndarray, U: np.ndarray, x_ref: np.ndarray, u_prev: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Residuals (B, m) and Jacobian (B, m, H*nu) from predicted states X (B, H, nx) and their
        sensitivities d X / d U (B, H, nx, H*nu), numpy."""
        (horizon, nx, nu), batch = (self.horizon, self.nx, self.nu), X.shape[0]
        n_var = horizon * nu
        r = self.residuals(
            X, U.reshape(batch, horizon, nu), x_ref.reshape(batch, horizon, nx), u_prev.reshape(batch, nu)
        )
        jac = np.empty((batch, r.shape[-1], n_var))
        np.matmul(self.weights[np][0], sens, out=jac[:, : horizon * nx].reshape(batch, horizon, nx, n_var))
        jac_u = self._input_jacobian(np)
        end = horizon * nx + jac_u.shape[0]
        jac[:, horizon * nx : end] = jac_u
        if self._limits is not None:
            jac[:, end:] = self.limit_jacobian(X, sens)
        return r, jac

    def input_jacobian(self) -> np.ndarray:
        """d(input residuals)/dU in numpy: constant, the input and input-rate residuals being linear in U."""
        return self._input_jacobian(np)

    def _input_jacobian(self, xp: ModuleType) -> Array:
        """d(input residuals)/dU, computed once per namespace."""
        if xp not in self._jac_u:
            _, w_r, w_d = self.weights[xp]
            n_var = self.horizon * self.nu
            eye_u = xp.eye(n_var, dtype=xp.float64).reshape(self.horizon, self.nu, n_var)
            parts = [(w_r @ eye_u).reshape(n_var, n_var)]
            if w_d is not None:
                shifted = cat([xp.zeros_like(eye_u[:1]), eye_u[:-1]], 0)
                parts.append((w_d @ (eye_u - shifted)).reshape(n_var, n_var))
            self._jac_u[xp] = cat(parts, 0)
        return self._jac_u[xp]
