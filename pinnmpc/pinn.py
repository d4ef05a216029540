"""The PINN as a plain nn.Module: x(t) = flow of the zero-hold system from x0 under u.

Besides the forward map it propagates tangents through the MLP (forward-mode
automatic differentiation written out for smooth activations): one pass gives
x(t) and dx/dt for the physics loss, or x(tau) and its Jacobian w.r.t. (x0, u)
for the controller, without extra reverse passes.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
from torch import Tensor, nn


def _tanh(a: Tensor) -> tuple[Tensor, Tensor]:
    """tanh and its derivative, reusing the value."""
    y = torch.tanh(a)
    return y, 1 - y * y


def _sin(a: Tensor) -> tuple[Tensor, Tensor]:
    """sin (SIREN-style) and its derivative."""
    return torch.sin(a), torch.cos(a)


def _silu(a: Tensor) -> tuple[Tensor, Tensor]:
    """SiLU (swish) and its derivative: smooth, non-saturating."""
    s = torch.sigmoid(a)
    return a * s, s * (1 + a * (1 - s))


def _softplus(a: Tensor) -> tuple[Tensor, Tensor]:
    """Softplus and its derivative."""
    return nn.functional.softplus(a), torch.sigmoid(a)


IC_MODES = ("hard", "gated", "soft")  # exact x(0) = x0; exact with relaxation gates; the paper's data loss
ACTIVATIONS: dict[str, Callable[[Tensor], tuple[Tensor, Tensor]]] = {
    "tanh": _tanh,
    "sin": _sin,
    "silu": _silu,
    "softplus": _softplus,
}


class TangentMLP(nn.Module):
    """MLP that can carry tangents along: y, dy = f(z), Df(z) dz for dz (..., k, in)."""

    def __init__(self, n_in: int, n_out: int, hidden: Sequence[int], activation: str) -> None:
        super().__init__()
        if activation not in ACTIVATIONS:
            raise ValueError(f"unknown activation {activation!r}; expected one of {sorted(ACTIVATIONS)} (smooth)")
        if not hidden or any(int(w) < 1 for w in hidden):
            raise ValueError(f"hidden layer widths must be positive integers, got {list(hidden)}")
        widths = [n_in, *[int(w) for w in hidden], n_out]
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(widths[:-1], widths[1:]))
        self.act = ACTIVATIONS[activation]
        for layer in self.layers:
            nn.init.xavier_normal_(layer.weight)
            nn.init.zeros_(layer.bias)

    def forward(self, z: Tensor) -> Tensor:
        """Plain evaluation, the cheapest path."""
        for layer in self.layers[:-1]:
            z = self.act(layer(z))[0]
        return self.layers[-1](z)

    def forward_tangent(self, z: Tensor, dz: Tensor) -> tuple[Tensor, Tensor]:
        """Value and directional derivatives; dz is (..., k, n_in) for k directions."""
        for layer in self.layers[:-1]:
            a = layer(z)
            da = dz @ layer.weight.T
            z, slope = self.act(a)
            dz = da * slope.unsqueeze(-2)
        last = self.layers[-1]
        return last(z), dz @ last.weight.T


class PINN(nn.Module):
    """Flow map (t, x0, u) -> x(t) with inputs normalised to [-1, 1] over the training box.

    ic='hard' builds the initial condition in, x = x0 + (t / t_max) * scale * N(.). ic='gated' adds a
    time gate g = 1 - exp(-t / T) per relaxation time T in time_basis, x = x0 + scale * sum_k g_k(t) N_k(.)
    with g_0 = t / t_max: heavily damped velocities relax within a few T, and a gate of that shape spares
    the network the steep boundary layer at small t. ic='soft' is the paper's plain output
    x = center + halfwidth * N(.), with x(0) = x0 learned from data points.
    """

    def __init__(
        self,
        state_low: Sequence[float],
        state_high: Sequence[float],
        input_low: Sequence[float],
        input_high: Sequence[float],
        t_max: float,
        hidden: Sequence[int] = (64, 64, 64, 64),
        activation: str = "tanh",
        ic: str = "hard",
        output_scale: Sequence[float] | None = None,
        time_basis: Sequence[float] = (),
    ) -> None:
        super().__init__()
        if ic not in IC_MODES:
            raise ValueError(f"unknown initial-condition mode {ic!r}; expected one of {list(IC_MODES)}")
        time_basis = [float(v) for v in time_basis]
        if any(not (v > 0 and math.isfinite(v)) for v in time_basis):
            raise ValueError(f"time_basis must hold positive relaxation times in s, got {time_basis}")
        if (ic == "gated") != bool(time_basis):
            raise ValueError(
                f"ic='gated' needs a non-empty time_basis and the other modes none; got ic={ic!r}, "
                f"time_basis={time_basis}"
            )
        if not t_max > 0:
            raise ValueError(f"t_max must be > 0, got {t_max}")
        self.config = {
            "state_low": [float(v) for v in state_low],
            "state_high": [float(v) for v in state_high],
            "input_low": [float(v) for v in input_low],
            "input_high": [float(v) for v in input_high],
            "t_max": float(t_max),
            "hidden": [int(w) for w in hidden],
            "activation": activation,
            "ic": ic,
            "output_scale": None if output_scale is None else [float(v) for v in output_scale],
            "time_basis": time_basis,
        }  # everything needed to rebuild the module from a checkpoint
        self.nx, self.nu = len(state_low), len(input_low)
        self.ic = ic
        self.exact_ic = ic != "soft"  # x(0) = x0 by construction
        self.t_max = float(t_max)
        low = torch.tensor([0.0, *state_low, *input_low], dtype=torch.float32)
        high = torch.tensor([t_max, *state_high, *input_high], dtype=torch.float32)
        if torch.any(high <= low):
            raise ValueError(
                f"training box must have low < high in every coordinate, got low={low.tolist()}, high={high.tolist()}"
            )
        self.register_buffer("in_center", (high + low) / 2)
        self.register_buffer("in_half", (high - low) / 2)
        if self.exact_ic:
            scale = (
                torch.ones(self.nx) if output_scale is None else torch.tensor(list(output_scale), dtype=torch.float32)
            )
            if scale.shape != (self.nx,) or torch.any(scale <= 0):
                raise ValueError(f"output_scale must be {self.nx} positive numbers, got {scale.tolist()}")
            self.register_buffer("out_scale", scale)
        else:
            self.register_buffer("out_scale", self.in_half[1 : 1 + self.nx].clone())
        self.register_buffer("out_center", self.in_center[1 : 1 + self.nx].clone())
        self.register_buffer("time_basis", torch.tensor(time_basis, dtype=torch.float32), persistent=False)
        self.n_gates = 1 + len(time_basis)
        self.net = TangentMLP(1 + self.nx + self.nu, self.nx * self.n_gates, hidden, activation)

    def _inputs(self, t: Tensor, x0: Tensor, u: Tensor) -> Tensor:
        """Normalised network input z in [-1, 1]^7 over the training box."""
        t, x0, u = torch.broadcast_tensors(t, x0[..., :1], u[..., :1])[0], x0, u
        return (torch.cat((t, x0, u), dim=-1) - self.in_center) / self.in_half

    def gates(self, t: Tensor) -> tuple[Tensor, Tensor]:
        """Time gates g(t) (..., n_gates), all zero at t = 0, and dg/dt."""
        ramp = torch.cat((t / self.t_max, 1.0 - torch.exp(-t / self.time_basis)), dim=-1)
        slope = torch.cat((torch.full_like(t, 1.0 / self.t_max), torch.exp(-t / self.time_basis) / self.time_basis), -1)
        return ramp, slope

    def _gated(self, g: Tensor, n: Tensor) -> Tensor:
        """sum_k g_k N_k: n (..., n_gates * nx) holds one head of nx outputs per gate."""
        return (g.unsqueeze(-1) * n.unflatten(-1, (self.n_gates, self.nx))).sum(-2)

    def _assemble(self, t: Tensor, x0: Tensor, n: Tensor) -> Tensor:
        """Network output to state, enforcing x(0) = x0 unless ic='soft'."""
        if self.exact_ic:
            return x0 + self.out_scale * self._gated(self.gates(t)[0], n)
        return self.out_center + self.out_scale * n

    def forward(self, t: Tensor, x0: Tensor, u: Tensor) -> Tensor:
        """x(t) for t (..., 1), x0 (..., nx), u (..., nu)."""
        return self._assemble(t, x0, self.net(self._inputs(t, x0, u)))

    def with_time_derivative(self, t: Tensor, x0: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """x(t) and dx/dt in one forward-mode pass, for the physics residual."""
        z = self._inputs(t, x0, u)
        dz = torch.zeros_like(z)
        dz[..., 0] = 1.0 / self.in_half[0]
        n, dn = self.net.forward_tangent(z, dz.unsqueeze(-2))
        dn = dn.squeeze(-2)
        if self.exact_ic:
            g, dg = self.gates(t)
            x = x0 + self.out_scale * self._gated(g, n)
            dxdt = self.out_scale * (self._gated(dg, n) + self._gated(g, dn))
            return x, dxdt
        return self.out_center + self.out_scale * n, self.out_scale * dn

    def with_jacobian(self, t: Tensor, x0: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """x(t) and d x(t) / d(x0, u) as (..., nx, nx + nu), for Gauss-Newton control."""
        z = self._inputs(t, x0, u)
        n_state_in = self.nx + self.nu
        eye = torch.eye(n_state_in, dtype=z.dtype, device=z.device) / self.in_half[1:]
        dz = torch.cat((torch.zeros(n_state_in, 1, dtype=z.dtype, device=z.device), eye), dim=-1)
        dz = dz.expand(*z.shape[:-1], n_state_in, z.shape[-1])
        n, dn = self.net.forward_tangent(z, dz)
        if self.exact_ic:
            g = self.gates(t)[0]
            x = x0 + self.out_scale * self._gated(g, n)
            jac = self.out_scale.unsqueeze(-1) * self._gated(g.unsqueeze(-2), dn).transpose(-1, -2)
            jac = jac + torch.eye(self.nx, n_state_in, dtype=z.dtype, device=z.device)
            return x, jac  # (..., nx, nx + nu)
        return self.out_center + self.out_scale * n, self.out_scale.unsqueeze(-1) * dn.transpose(-1, -2)
