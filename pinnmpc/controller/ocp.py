"""The horizon optimal control problem as a batched nonlinear least-squares problem on a surrogate."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from pinnmpc.surrogate import Surrogate


def psd_sqrt(matrix: Sequence[Sequence[float]] | Sequence[float], n: int, name: str) -> Tensor:
    """Symmetric square root W of a PSD weight (W^T W = matrix); a flat list is a diagonal."""
    m = torch.as_tensor(matrix, dtype=torch.float64)
    if m.ndim == 1:
        m = torch.diag(m)
    if m.shape != (n, n):
        raise ValueError(f"{name} must be {n} diagonal entries or an {n}x{n} matrix, got shape {tuple(m.shape)}")
    if not torch.all(torch.isfinite(m)):
        raise ValueError(f"{name} has non-finite entries: {m.tolist()}")
    if not torch.allclose(m, m.T, atol=1e-12):
        raise ValueError(f"{name} must be symmetric, got {m.tolist()}")
    eig, vec = torch.linalg.eigh(m)
    if eig.min() < -1e-12 * max(1.0, float(eig.abs().max())):
        raise ValueError(f"{name} must be positive semidefinite; its smallest eigenvalue is {float(eig.min()):.3g}")
    return vec @ torch.diag(eig.clamp_min(0).sqrt()) @ vec.T


class HorizonOCP:
    """min_U sum_i ||W_q (x_ref_i - x_i)||^2 + ||W_r u_i||^2 + ||W_d (u_i - u_{i-1})||^2, x_{i+1} = s.step(x_i, u_i)."""

    def __init__(
        self,
        surrogate: Surrogate,
        horizon: int,
        Q: Sequence,  # noqa: N803 - names from the field
        R: Sequence,  # noqa: N803
        R_rate: Sequence | None = None,  # noqa: N803
    ) -> None:
        if int(horizon) < 1:
            raise ValueError(f"horizon must be >= 1, got {horizon}")
        self.surrogate = surrogate
        self.horizon = int(horizon)
        nx, nu = surrogate.nx, surrogate.nu
        self.nx, self.nu = nx, nu
        self.w_q = psd_sqrt(Q, nx, "Q")
        self.w_r = psd_sqrt(R, nu, "R")
        self.w_d = None if R_rate is None else psd_sqrt(R_rate, nu, "R_rate")
        if self.w_d is not None and not torch.any(self.w_d != 0):
            self.w_d = None

    @property
    def n_residuals(self) -> int:
        """Length of the stacked residual vector per problem."""
        per_step = self.nx + self.nu + (self.nu if self.w_d is not None else 0)
        return self.horizon * per_step

    def rollout(self, x0: Tensor, U: Tensor) -> Tensor:  # noqa: N803
        """Predicted states x_1..x_H (..., H, nx) by self-loop of the surrogate."""
        xs, x = [], x0
        for i in range(self.horizon):
            x = self.surrogate.step(x, U[..., i, :])
            xs.append(x)
        return torch.stack(xs, dim=-2)

    def residuals(self, X: Tensor, U: Tensor, x_ref: Tensor, u_prev: Tensor) -> Tensor:  # noqa: N803
        """Stacked weighted residuals (..., m); the cost is their squared norm."""
        parts = [((X - x_ref) @ self.w_q.T).flatten(-2), (U @ self.w_r.T).flatten(-2)]
        if self.w_d is not None:
            du = U - torch.cat((u_prev.unsqueeze(-2), U[..., :-1, :]), dim=-2)
            parts.append((du @ self.w_d.T).flatten(-2))
        return torch.cat(parts, dim=-1)

    def cost(self, x0: Tensor, U: Tensor, x_ref: Tensor, u_prev: Tensor) -> Tensor:  # noqa: N803
        """Horizon cost per problem (...,)."""
        return self.residuals(self.rollout(x0, U), U, x_ref, u_prev).square().sum(-1)

    def residuals_and_jacobian(self, x0: Tensor, U: Tensor, x_ref: Tensor, u_prev: Tensor) -> tuple[Tensor, Tensor]:  # noqa: N803
        """Residuals (B, m) and their Jacobian (B, m, H*nu) from step Jacobians chained along the horizon."""
        batch, n_var = x0.shape[:-1], self.horizon * self.nu
        sens = torch.zeros(*batch, self.nx, n_var, dtype=x0.dtype)  # d x_i / d U
        xs, sens_list, x = [], [], x0
        for i in range(self.horizon):
            x, a, b = self.surrogate.step_with_jacobian(x, U[..., i, :])
            sens = a @ sens
            sens[..., :, i * self.nu : (i + 1) * self.nu] += b
            xs.append(x)
            sens_list.append(sens)
        X = torch.stack(xs, dim=-2)  # noqa: N806
        r = self.residuals(X, U, x_ref, u_prev)
        jac_x = self.w_q @ torch.stack(sens_list, dim=-3)  # (B, H, nx, n_var)
        eye_u = torch.eye(n_var, dtype=x0.dtype).reshape(self.horizon, self.nu, n_var)
        parts = [jac_x.flatten(-3, -2), (self.w_r @ eye_u).flatten(-3, -2).expand(*batch, -1, -1)]
        if self.w_d is not None:
            shifted = torch.cat((torch.zeros_like(eye_u[:1]), eye_u[:-1]), dim=0)
            parts.append((self.w_d @ (eye_u - shifted)).flatten(-3, -2).expand(*batch, -1, -1))
        return r, torch.cat(parts, dim=-2)
