"""The PINN as a plain nn.Module: x(t) = flow of the zero-hold system from x0 under u.

Besides the forward map it propagates tangents through the MLP (forward-mode
automatic differentiation written out for smooth activations): one pass gives
x(t) and dx/dt for the physics loss, or x(tau) and its Jacobian w.r.t. (x0, u)
for the controller, without extra reverse passes.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor, nn

from pinnmpc.surrogate import mlp
from pinnmpc.surrogate.activations import TORCH, check_activation
from pinnmpc.surrogate.prior import ArmPrior, check_prior

IC_MODES = ("hard", "gated", "soft")  # exact x(0) = x0; exact with relaxation gates; the paper's data loss


def _checked_prior(prior: dict | None, ic: str, second_order: bool) -> dict | None:
    """prior as {'kind', 'system'[, 'dynamics']}: a known kind, on a first-order network with an exact initial
    condition (dynamics: the arm's description, which networks since 2026-11-26 carry; older ones name it)."""
    if prior is None:
        return None
    if not isinstance(prior, dict) or not {"kind", "system"} <= set(prior) <= {"kind", "system", "dynamics"}:
        raise ValueError(f"prior must be null or {{'kind': ..., 'system': ..., 'dynamics': ...}}, got {prior!r}")
    if prior.get("dynamics") is not None and not isinstance(prior["dynamics"], dict):
        raise ValueError(f"prior dynamics must be the arm's description (a dict), got {prior['dynamics']!r}")
    check_prior(prior["kind"])
    if ic == "soft" or second_order:
        raise ValueError(
            f"a prior needs a first-order network with an exact initial condition; got ic={ic!r}, "
            f"second_order={second_order}"
        )
    checked = {"kind": str(prior["kind"]), "system": str(prior["system"])}
    return checked if prior.get("dynamics") is None else {**checked, "dynamics": prior["dynamics"]}


def _checked_sums(angle_sums: Sequence[Sequence[int]], periodic: Sequence[int]) -> list[list[int]]:
    """angle_sums as sorted index lists, each of two or more distinct periodic coordinates, none twice."""
    sums = [sorted(int(i) for i in coords) for coords in angle_sums]
    for coords in sums:
        if len(coords) < 2 or len(set(coords)) != len(coords) or not set(coords) <= set(periodic):
            raise ValueError(
                f"angle_sums must list sums of two or more distinct periodic state indices {list(periodic)}, "
                f"got {[list(c) for c in angle_sums]}"
            )
    if len({tuple(c) for c in sums}) != len(sums):
        raise ValueError(f"angle_sums lists a sum twice: {sums}")
    return sums


class TangentMLP(nn.Module):
    """MLP that can carry tangents along: y, dy = f(z), Df(z) dz for dz (..., k, in); the passes are
    pinnmpc.surrogate.mlp's, over torch."""

    def __init__(self, n_in: int, n_out: int, hidden: Sequence[int], activation: str) -> None:
        super().__init__()
        self.activation = check_activation(activation)
        if not hidden or any(int(w) < 1 for w in hidden):
            raise ValueError(f"hidden layer widths must be positive integers, got {list(hidden)}")
        widths = [n_in, *[int(w) for w in hidden], n_out]
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(widths[:-1], widths[1:]))
        for layer in self.layers:
            nn.init.xavier_normal_(layer.weight)
            nn.init.zeros_(layer.bias)

    def pairs(self) -> list[tuple[Tensor, Tensor]]:
        """The layers as (W, b) pairs, as the passes take them."""
        return [(layer.weight, layer.bias) for layer in self.layers]

    def forward(self, z: Tensor) -> Tensor:
        """Plain evaluation, the cheapest path."""
        return mlp.value(TORCH, self.pairs(), self.activation, z)

    def forward_tangent(self, z: Tensor, dz: Tensor) -> tuple[Tensor, Tensor]:
        """Value and directional derivatives; dz is (..., k, n_in) for k directions."""
        return mlp.tangent(TORCH, self.pairs(), self.activation, z, dz)

    def forward_second(self, z: Tensor, dz: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Value, first and second derivative along one direction dz (..., n_in) in which the input is linear."""
        return mlp.second(TORCH, self.pairs(), self.activation, z, dz)

    def forward_mixed(self, z: Tensor, dt: Tensor, dd: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Value, derivative along dt (..., n_in), along each of dd (..., k, n_in), and the mixed second ones."""
        return mlp.mixed(TORCH, self.pairs(), self.activation, z, dt, dd)


def time_gates(t: Tensor, t_max: float, time_basis: Tensor) -> tuple[Tensor, Tensor]:
    """Gates (t / t_max, 1 - exp(-t / T_k)) for t (..., 1) and their slopes: the time shapes of ic='gated'."""
    ramp = torch.cat((t / t_max, 1.0 - torch.exp(-t / time_basis)), dim=-1)
    slope = torch.cat((torch.full_like(t, 1.0 / t_max), torch.exp(-t / time_basis) / time_basis), -1)
    return ramp, slope


class PINN(nn.Module):
    """Flow map (t, x0, u) -> x(t) with inputs normalised to [-1, 1] over the training box.

    ic='hard' builds the initial condition in, x = x0 + (t / t_max) * scale * N(.). ic='gated' adds a
    time gate g = 1 - exp(-t / T) per relaxation time T in time_basis, x = x0 + scale * sum_k g_k(t) N_k(.)
    with g_0 = t / t_max: heavily damped velocities relax within a few T, and a gate of that shape spares
    the network the steep boundary layer at small t. ic='soft' is the paper's plain output
    x = center + halfwidth * N(.), with x(0) = x0 learned from data points.

    periodic lists state coordinates the dynamics see only through sin and cos (joint angles): the network
    gets sin and cos of them instead of the normalised value, so the flow increment it has to represent is
    smooth on the circle (no seam at the box edge, no sine to build from tanh) and holds beyond the box.
    angle_sums lists sums of periodic coordinates whose sin and cos are further inputs: the absolute link
    angles of an arm whose joint axes are parallel (q1 + q2, q1 + q2 + q3 of a planar arm), in which its gravity
    and inertia terms are single sines; from the joint angles alone a network has to build them as products.

    second_order=True is for mechanical systems x = (q, dq/dt): the network models the positions only,
    q = q0 + v0 t + scale_v * sum_k G_k(t) N_k(.) with G_k the time integral of gate g_k, and the velocity
    is its exact time derivative. dq/dt = v then holds by construction (in the first-order form its
    residual is the largest source of position error at tau), and both q(0) = q0 and v(0) = v0 are exact.

    The keyword defaults are conf/model/pinn.yaml's where they need no system (silu, 4 x 64); the initial condition
    defaults to hard because the gated one needs the system's time basis, which `python -m pinnmpc.train` adds
    (tests/test_controller_settings.py holds the two alike). The paper's network is activation="tanh".
    """

    def __init__(
        self,
        state_low: Sequence[float],
        state_high: Sequence[float],
        input_low: Sequence[float],
        input_high: Sequence[float],
        t_max: float,
        hidden: Sequence[int] = (64, 64, 64, 64),
        activation: str = "silu",
        ic: str = "hard",
        output_scale: Sequence[float] | None = None,
        time_basis: Sequence[float] = (),
        second_order: bool = False,
        periodic: Sequence[int] = (),
        angle_sums: Sequence[Sequence[int]] = (),
        prior: dict | None = None,
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
        if second_order and (ic == "soft" or len(state_low) % 2):
            raise ValueError(
                "second_order=True needs an exact initial condition (ic='hard' or 'gated') and a state "
                f"(positions, velocities) of even dimension; got ic={ic!r}, state dimension {len(state_low)}"
            )
        periodic = [int(i) for i in periodic]
        if len(set(periodic)) != len(periodic) or any(not 0 <= i < len(state_low) for i in periodic):
            raise ValueError(f"periodic must list distinct state indices in [0, {len(state_low)}), got {periodic}")
        angle_sums = _checked_sums(angle_sums, periodic)
        prior = _checked_prior(prior, ic, second_order)
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
            "second_order": bool(second_order),
            "periodic": periodic,
            "angle_sums": angle_sums,
            "prior": prior,
        }  # everything needed to rebuild the module from a checkpoint
        self.nx, self.nu = len(state_low), len(input_low)
        self.ic = ic
        self.exact_ic = ic != "soft"  # x(0) = x0 by construction
        self.second_order = bool(second_order)
        self.nq = self.nx // 2
        self.n_head = self.nq if self.second_order else self.nx  # network outputs per time gate
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
        self.periodic = periodic
        self.register_buffer("angles", torch.tensor(periodic, dtype=torch.long), persistent=False)  # x0 columns
        self.register_buffer("sin_cols", self.angles + 1, persistent=False)  # their columns of the network input
        n_lin = 1 + self.nx + self.nu  # t, x0, u; periodic x0 columns hold the sine, their cosines follow
        self.register_buffer("cos_cols", torch.arange(len(periodic), dtype=torch.long) + n_lin, persistent=False)
        sum_map = torch.zeros(len(angle_sums), self.nx)
        for row, coords in zip(sum_map, angle_sums):
            row[coords] = 1.0
        self.register_buffer("sum_map", sum_map, persistent=False)  # (n_sums, nx): the angle sums of x0
        n_trig = len(periodic) + 2 * len(angle_sums)  # cosines of the periodic states, then sin and cos of the sums
        self.net = TangentMLP(n_lin + n_trig, self.n_head * self.n_gates, hidden, activation)
        # no parameters, no state; the arm from its description (older networks: by its system name)
        self.prior = None if prior is None else ArmPrior(prior.get("dynamics") or prior["system"], prior["kind"], t_max)
        # the prior takes the arm's inputs, the first of the network's (a network given the previous input has more)
        self.prior_nu = self.nu if self.prior is None else len(self.prior.arm.input_names)

    @property
    def sum_columns(self) -> tuple[slice, slice]:
        """Columns of the network input holding the sines and the cosines of the angle sums (the last ones)."""
        n_sums = len(self.sum_map)
        end = self.net.layers[0].in_features
        return slice(end - 2 * n_sums, end - n_sums), slice(end - n_sums, end)

    @property
    def head_scale(self) -> Tensor:
        """Output scale of the network heads: the velocity part of out_scale for second-order models."""
        return self.out_scale[self.nx - self.n_head :]

    @property
    def residual_unit(self) -> Tensor:
        """Typical size of dx/dt - f per state (output scale over the time span): the physics loss divides by it."""
        return self.out_scale / self.t_max

    def _inputs(self, t: Tensor, x0: Tensor, u: Tensor) -> Tensor:
        """Normalised network input z in [-1, 1] over the training box, periodic states as (sin, cos)."""
        t, x0, u = torch.broadcast_tensors(t, x0[..., :1], u[..., :1])[0], x0, u
        z = (torch.cat((t, x0, u), dim=-1) - self.in_center) / self.in_half
        if not self.periodic:
            return z
        angle = x0[..., self.angles]
        parts = [z.index_copy(-1, self.sin_cols, torch.sin(angle)), torch.cos(angle)]
        if len(self.sum_map):
            total = x0 @ self.sum_map.T
            parts += [torch.sin(total), torch.cos(total)]
        return torch.cat(parts, dim=-1)

    def gates(self, t: Tensor) -> tuple[Tensor, Tensor]:
        """Time gates g(t) (..., n_gates), all zero at t = 0, and dg/dt."""
        return time_gates(t, self.t_max, self.time_basis)

    def gate_integrals(self, t: Tensor) -> Tensor:
        """G_k(t) = integral of g_k from 0 to t: zero value and slope at t = 0, for second-order models."""
        decay = 1.0 - torch.exp(-t / self.time_basis)
        return torch.cat((t * t / (2 * self.t_max), t - self.time_basis * decay), dim=-1)

    def _gated(self, g: Tensor, n: Tensor) -> Tensor:
        """sum_k g_k N_k: n (..., n_gates * n_head) holds one head of n_head outputs per gate."""
        return (g.unsqueeze(-1) * n.unflatten(-1, (self.n_gates, self.n_head))).sum(-2)

    def _time_tangent(self, z: Tensor) -> Tensor:
        """dz/dt of the normalised input."""
        dz = torch.zeros_like(z)
        dz[..., 0] = 1.0 / self.in_half[0]
        return dz

    def _second_order_gates(self, t: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Gates g_k, their slopes and their integrals G_k at t, computed once per call of the network."""
        g, dg = self.gates(t)
        return g, dg, self.gate_integrals(t)

    def _kinematic(self, t: Tensor, x0: Tensor, g: Tensor, big_g: Tensor, n: Tensor, dn: Tensor) -> Tensor:
        """Second-order state (q, v) from the network value N and its time derivative dN/dt."""
        q0, v0 = x0[..., : self.nq], x0[..., self.nq :]
        q = q0 + v0 * t + self.head_scale * self._gated(big_g, n)
        v = v0 + self.head_scale * (self._gated(g, n) + self._gated(big_g, dn))
        return torch.cat((q, v), dim=-1)

    def _start(self, t: Tensor, x0: Tensor, u: Tensor) -> tuple[Tensor, Tensor | None]:
        """What the gated network output is added to, and its time derivative: x0 (None), or the prior's x_p(t)."""
        return (x0, None) if self.prior is None else self.prior(t, x0, u[..., : self.prior_nu])

    def _assemble(self, t: Tensor, x0: Tensor, u: Tensor, n: Tensor) -> Tensor:
        """Network output to state, enforcing x(0) = x0 unless ic='soft'."""
        if self.exact_ic:
            return self._start(t, x0, u)[0] + self.out_scale * self._gated(self.gates(t)[0], n)
        return self.out_center + self.out_scale * n

    def forward(self, t: Tensor, x0: Tensor, u: Tensor) -> Tensor:
        """x(t) for t (..., 1), x0 (..., nx), u (..., nu)."""
        z = self._inputs(t, x0, u)
        if self.second_order:
            n, dn = self.net.forward_tangent(z, self._time_tangent(z).unsqueeze(-2))
            g, _, big_g = self._second_order_gates(t)
            return self._kinematic(t, x0, g, big_g, n, dn.squeeze(-2))
        return self._assemble(t, x0, u, self.net(z))

    def with_time_derivative(self, t: Tensor, x0: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """x(t) and dx/dt in one forward-mode pass, for the physics residual."""
        z = self._inputs(t, x0, u)
        dz = self._time_tangent(z)
        if self.second_order:
            return self._second_order_time_derivative(t, x0, *self.net.forward_second(z, dz))
        n, dn = self.net.forward_tangent(z, dz.unsqueeze(-2))
        dn = dn.squeeze(-2)
        if self.exact_ic:
            g, dg = self.gates(t)
            start, dstart = self._start(t, x0, u)
            x = start + self.out_scale * self._gated(g, n)
            dxdt = self.out_scale * (self._gated(dg, n) + self._gated(g, dn))
            return x, dxdt if dstart is None else dxdt + dstart
        return self.out_center + self.out_scale * n, self.out_scale * dn

    def _second_order_time_derivative(
        self, t: Tensor, x0: Tensor, n: Tensor, dn: Tensor, ddn: Tensor
    ) -> tuple[Tensor, Tensor]:
        """(q, v) and (v, dv/dt) of a second-order model from N and its first two time derivatives."""
        g, dg, big_g = self._second_order_gates(t)
        x = self._kinematic(t, x0, g, big_g, n, dn)
        acc = self.head_scale * (self._gated(dg, n) + 2 * self._gated(g, dn) + self._gated(big_g, ddn))
        return x, torch.cat((x[..., self.nq :], acc), dim=-1)

    def _state_tangents(self, z: Tensor) -> Tensor:
        """dz/d(x0, u) of the network input, one row per state and input coordinate."""
        n_state_in = self.nx + self.nu
        eye = torch.eye(n_state_in, dtype=z.dtype, device=z.device) / self.in_half[1:]
        dz = torch.zeros(n_state_in, z.shape[-1], dtype=z.dtype, device=z.device)
        dz[:, 1 : 1 + n_state_in] = eye
        dz = dz.expand(*z.shape[:-1], n_state_in, z.shape[-1])
        if not self.periodic:
            return dz
        dz = dz.clone()
        dz[..., self.angles, self.sin_cols] = z[..., self.cos_cols]  # d sin(q) / dq = cos(q), read off the input
        dz[..., self.angles, self.cos_cols] = -z[..., self.sin_cols]
        if len(self.sum_map):  # d sin(a.x) / dx = cos(a.x) a for each sum a, on the x0 rows
            sums = self.sum_map.T.to(z.dtype)  # (nx, n_sums)
            sin_cols, cos_cols = self.sum_columns
            sin, cos = z[..., sin_cols].unsqueeze(-2), z[..., cos_cols].unsqueeze(-2)
            dz[..., : self.nx, sin_cols] = sums * cos
            dz[..., : self.nx, cos_cols] = -sums * sin
        return dz

    def _second_order_jacobian(self, t: Tensor, x0: Tensor, z: Tensor) -> tuple[Tensor, Tensor]:
        """(q, v)(t) and its Jacobian for a second-order model: needs the mixed derivatives d2N/dt d(x0, u)."""
        n, dn, jn, jdn = self.net.forward_mixed(z, self._time_tangent(z), self._state_tangents(z))
        g, _, big_g = self._second_order_gates(t)
        gk, big_gk = g.unsqueeze(-2), big_g.unsqueeze(-2)  # one gate row for all k tangent directions
        scale = self.head_scale.unsqueeze(-1)
        jq = scale * self._gated(big_gk, jn).transpose(-1, -2)
        jv = scale * (self._gated(gk, jn) + self._gated(big_gk, jdn)).transpose(-1, -2)
        n_state_in = self.nx + self.nu
        eye = torch.eye(self.nx, n_state_in, dtype=z.dtype, device=z.device)
        jac = torch.cat((jq, jv), dim=-2) + eye
        jac[..., : self.nq, self.nq : self.nx] += t.unsqueeze(-1) * torch.eye(self.nq, dtype=z.dtype, device=z.device)
        return self._kinematic(t, x0, g, big_g, n, dn), jac

    def with_jacobian(self, t: Tensor, x0: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """x(t) and d x(t) / d(x0, u) as (..., nx, nx + nu), for Gauss-Newton control."""
        z = self._inputs(t, x0, u)
        if self.second_order:
            return self._second_order_jacobian(t, x0, z)
        dz = self._state_tangents(z)
        n, dn = self.net.forward_tangent(z, dz)
        if self.exact_ic:
            g = self.gates(t)[0]
            jac = self.out_scale.unsqueeze(-1) * self._gated(g.unsqueeze(-2), dn).transpose(-1, -2)
            if self.prior is None:
                start, dstart = x0, torch.eye(self.nx, self.nx + self.nu, dtype=z.dtype, device=z.device)
            else:
                start, dstart = self.prior.with_jacobian(t, x0, u[..., : self.prior_nu])
                if self.prior_nu < self.nu:  # inputs the prior does not take (the previous input)
                    dstart = torch.nn.functional.pad(dstart, (0, self.nu - self.prior_nu))
            return start + self.out_scale * self._gated(g, n), jac + dstart  # jac (..., nx, nx + nu)
        return self.out_center + self.out_scale * n, self.out_scale.unsqueeze(-1) * dn.transpose(-1, -2)
