"""The trained network as plain numpy: batch-1 controller calls are dominated by per-op overhead, which
numpy has less of than torch. Same weights and activations as pinnmpc.surrogate.network.PINN, with what is
constant at t = tau folded in, and the tangents riding in the values' GEMM (pinnmpc.surrogate.mlp.tangent is the
plain pass it is tested against)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial
from typing import ClassVar

import numpy as np
import torch

from pinnmpc.surrogate import mlp
from pinnmpc.surrogate.activations import NUMPY, TANGENTS, VALUES, with_curvature
from pinnmpc.surrogate.network import PINN
from pinnmpc.surrogate.prior import CompiledPrior
from pinnmpc.systems.base import Box


def _np(t: torch.Tensor) -> np.ndarray:
    """A float64 numpy copy, detached from the torch module."""
    return t.detach().double().numpy().copy()


def _folded_input(model: PINN, tau: float) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """First layer on raw (x0, u) with t = tau and the input normalisation folded in (periodic states and angle
    sums through their sine and cosine weights), and its d/dt."""
    w1, b1 = _np(model.net.layers[0].weight), _np(model.net.layers[0].bias)
    center, half = _np(model.in_center), _np(model.in_half)
    n_raw, periodic = model.nx + model.nu, np.asarray(model.periodic, dtype=np.intp)
    w_in = w1[:, 1 : 1 + n_raw] / half[1:]
    w_in[:, periodic] = 0.0  # periodic states enter through w_sin, w_cos only
    b_in = b1 + w1[:, 0] * (tau - center[0]) / half[0] - w_in @ center[1:]
    cos_cols = 1 + n_raw + np.arange(len(periodic))  # network input: cosines of the periodic states, then the sums'
    sum_sin, sum_cos = (np.arange(w1.shape[1])[cols] for cols in model.sum_columns)
    first = {
        "w_in": np.ascontiguousarray(w_in.T),
        "b_in": b_in,
        "periodic": periodic,
        "sums": _np(model.sum_map) if len(model.sum_map) else None,
        "w_sin": np.ascontiguousarray(w1[:, np.concatenate((1 + periodic, sum_sin))].T),
        "w_cos": np.ascontiguousarray(w1[:, np.concatenate((cos_cols, sum_cos))].T),
    }
    return first, w1[:, 0] / half[0]


def _facts(model: PINN, tau: float, state_names: Sequence[str], input_names: Sequence[str]) -> dict[str, object]:
    """What the FlowMap interface asks besides the maths: tau, names and the network's training boxes."""
    cfg = model.config
    return {
        "tau": float(tau),
        "state_names": tuple(state_names),
        "input_names": tuple(input_names),
        "state_box": Box(cfg["state_low"], cfg["state_high"]),
        "input_box": Box(cfg["input_low"], cfg["input_high"]),
    }


class BlockDiagonal:
    """W^T of a block-diagonal layer (a merged multi-stage network): z @ W multiplies block by block, skipping
    the zeros a single GEMM would multiply."""

    __array_ufunc__ = None  # so that `z @ block_diagonal` comes here instead of numpy's matmul

    def __init__(self, blocks: list[np.ndarray]) -> None:
        self.blocks = [np.ascontiguousarray(b) for b in blocks]
        edges = np.cumsum([0, *(b.shape[0] for b in self.blocks)]).tolist()
        self.parts = [(slice(a, b), block) for a, b, block in zip(edges[:-1], edges[1:], self.blocks)]

    @classmethod
    def split(cls, w: np.ndarray) -> BlockDiagonal | np.ndarray:
        """The blocks of a square W^T that is block-diagonal (zeros off the blocks), else W^T itself."""
        n = w.shape[0]
        if w.shape != (n, n):
            return w
        edges, start = [], 0
        for i in range(1, n):  # a block ends at i where nothing couples rows < i with columns >= i and vice versa
            if not (w[start:i, i:].any() or w[i:, start:i].any()):
                edges.append(i)
                start = i
        if not edges:
            return w
        bounds = [0, *edges, n]
        return cls([w[a:b, a:b] for a, b in zip(bounds[:-1], bounds[1:])])

    def __rmatmul__(self, z: np.ndarray) -> np.ndarray:
        """z @ W for z (..., width)."""
        out = np.empty(z.shape)
        for cols, block in self.parts:  # python slices: cheaper to apply than numpy integers at batch 1
            np.matmul(z[..., cols], block, out=out[..., cols])
        return out


def _hidden(model: PINN) -> list[tuple[np.ndarray | BlockDiagonal, np.ndarray]]:
    """Hidden-to-hidden layers as (W^T, b), block by block where a merged network's layers are block-diagonal."""
    return [(BlockDiagonal.split(np.ascontiguousarray(_np(m.weight).T)), _np(m.bias)) for m in model.net.layers[1:-1]]


def _gate_sum(model: PINN, g: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Output layer collapsed over the time gates at one time: W^T (width, n_head) and b, times the head scale."""
    w, b = _np(model.net.layers[-1].weight), _np(model.net.layers[-1].bias)
    g, heads = _np(g), (model.n_gates, model.n_head)
    scale = _np(model.head_scale)
    w, b = np.einsum("k,kij->ij", g, w.reshape(*heads, -1)), g @ b.reshape(heads)
    return (scale[:, None] * w).T, scale * b


@dataclass
class NumpyFlow:
    """x(tau) and its Jacobian w.r.t. (x0, u) for a fixed tau: weights stored transposed (z @ W), the input
    normalisation folded into the first layer, the time gates, output scale and centre into the last."""

    w_in: np.ndarray  # (nx + nu, width): first layer acting on raw (x0, u)
    b_in: np.ndarray  # (width,): first-layer bias with t = tau and the normalisation folded in
    hidden: list[tuple[np.ndarray, np.ndarray]]  # hidden-to-hidden layers (W^T, b)
    w_out: np.ndarray  # (width, nx): output layer giving x(tau) - x0 (hard IC) or x(tau) (soft IC)
    b_out: np.ndarray  # (nx,)
    hard_ic: bool
    activation: str
    nx: int
    nu: int
    periodic: np.ndarray | None = None  # indices of the states entering as (sin, cos); their rows of w_in are zero
    sums: np.ndarray | None = None  # (n_sums, nx): angle sums entering as (sin, cos) too (None: none)
    w_sin: np.ndarray | None = None  # (n_periodic + n_sums, width): first layer acting on sin of the angles, sums
    w_cos: np.ndarray | None = None  # (n_periodic + n_sums, width): ... and on their cosines
    tau: float = 0.0  # the period folded in, s: the FlowMap facts (pinnmpc.surrogate.flowmap) from here on
    state_names: tuple[str, ...] = ()  # empty: x0, x1, ...
    input_names: tuple[str, ...] = ()  # empty: u0, u1, ...
    state_box: Box | None = None  # the network's training box (None: unbounded)
    input_box: Box | None = None
    start: CompiledPrior | None = None  # the prior at tau (pinnmpc.surrogate.prior): the output adds to x_p, not to x0
    prior_nu: int | None = None  # the inputs the prior takes, the first ones (None: all; fewer: the previous input)

    array_api: ClassVar[str] = "numpy"

    @property
    def approximate_jacobians(self) -> bool:
        """Whether A, B are not the derivatives of step(): a prior whose Jacobian stands in (solvers then treat
        their Gauss-Newton models as inexact, as for controller.model=exact_values)."""
        return self.start is not None and self.start.stand_in_jacobian

    def __post_init__(self) -> None:
        if self.periodic is None:
            self.periodic = np.empty(0, dtype=np.intp)
        if self.prior_nu is None:
            self.prior_nu = self.nu
        self.state_names = tuple(self.state_names) or tuple(f"x{i}" for i in range(self.nx))
        self.input_names = tuple(self.input_names) or tuple(f"u{i}" for i in range(self.nu))
        self.state_box = self.state_box or Box([-np.inf] * self.nx, [np.inf] * self.nx)
        self.input_box = self.input_box or Box([-np.inf] * self.nu, [np.inf] * self.nu)
        self.w_trig = np.concatenate((self.w_sin, self.w_cos)) if self.periodic.size else None  # (sin, cos) @ w_trig
        self.eye = np.eye(self.nx)  # dx/dx0 of the skip connection x0 + ...
        self.act = partial(TANGENTS[self.activation], NUMPY)
        self.value = partial(VALUES[self.activation], NUMPY)

    @classmethod
    def from_pinn(
        cls,
        model: PINN,
        tau: float,
        state_names: Sequence[str] = (),
        input_names: Sequence[str] = (),
    ) -> NumpyFlow:
        """Copy float64 weights out of the torch module and fold in what is constant at t = tau."""
        facts = _facts(model, tau, state_names, input_names)
        if model.second_order:
            return SecondOrderNumpyFlow.from_second_order_pinn(model, tau, facts)
        if model.prior is not None:
            facts["start"], facts["prior_nu"] = model.prior.compiled(tau), model.prior_nu
        first, _ = _folded_input(model, tau)
        hard = model.exact_ic
        if hard:  # the time gates are constants at t = tau: x(tau) - x0 = scale * sum_k g_k N_k
            w_out, b_out = _gate_sum(model, model.gates(torch.full((1,), float(tau), dtype=model.out_scale.dtype))[0])
        else:
            w, scale = _np(model.net.layers[-1].weight), _np(model.out_scale)
            w_out = (scale[:, None] * w).T
            b_out = scale * _np(model.net.layers[-1].bias) + _np(model.out_center)
        return cls(
            hidden=_hidden(model), w_out=np.ascontiguousarray(w_out), b_out=b_out, hard_ic=hard,
            activation=model.config["activation"], nx=model.nx, nu=model.nu, **first, **facts,
        )  # fmt: skip

    def numpy_flow(self) -> NumpyFlow:
        """Itself: the FlowMap's numpy fast path."""
        return self

    def _check(self, x0: np.ndarray, u: np.ndarray) -> None:
        """One clear error for arrays of another system, not a reshape or matmul message from deep inside."""
        if x0.shape[-1:] != (self.nx,) or u.shape[-1:] != (self.nu,):
            raise ValueError(f"x0 {x0.shape} and u {u.shape}; expected (..., {self.nx}) and (..., {self.nu})")

    def _first_layer(self, x0: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray] | None]:
        """Pre-activation of the first layer (GEMMs on x0 and u, no concatenation), and (sin, cos) of the
        periodic states and angle sums, (..., n_periodic + n_sums) each, or None without periodic states."""
        a = x0 @ self.w_in[: self.nx]
        a += u @ self.w_in[self.nx :]
        a += self.b_in
        if not self.periodic.size:
            return a, None
        angle = x0[..., self.periodic]
        if self.sums is not None:
            angle = np.concatenate((angle, x0 @ self.sums.T), axis=-1)
        trig = np.sin(angle), np.cos(angle)
        a += np.concatenate(trig, axis=-1) @ self.w_trig
        return a, trig

    def _angle_rows(self, trig: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray | None:
        """d(first-layer pre-activation)/d(angle), (batch, n_periodic + n_sums, width): cos w_sin - sin w_cos."""
        if trig is None:
            return None
        sin, cos = trig
        return cos[..., None] * self.w_sin - sin[..., None] * self.w_cos

    def _input_tangents(self, factor: np.ndarray, angle_rows: np.ndarray | None, out: np.ndarray) -> None:
        """factor * d(first-layer pre-activation)/d(x0, u) into out (batch, nx + nu, width)."""
        np.multiply(factor[:, None, :], self.w_in, out=out)
        if angle_rows is None:
            return
        n_periodic = self.periodic.size
        out[:, self.periodic] = factor[:, None, :] * angle_rows[:, :n_periodic]
        if self.sums is not None:  # a sum's row reaches every state it adds up
            out[:, : self.nx] += factor[:, None, :] * (self.sums.T @ angle_rows[:, n_periodic:])

    def step(self, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
        """x(tau) for x0 (..., nx), u (..., nu)."""
        self._check(x0, u)
        z = self.value(self._first_layer(x0, u)[0])
        n = mlp.value(NUMPY, [*self.hidden, (self.w_out, self.b_out)], self.activation, z)
        if self.start is not None:
            lead = x0.shape[:-1]
            arm_u = u.reshape(-1, self.nu)[:, : self.prior_nu]
            return self.start.value(x0.reshape(-1, self.nx), arm_u)[0].reshape(*lead, self.nx) + n
        return x0 + n if self.hard_ic else n

    def step_with_jacobian(self, x0: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x(tau), A = dx/dx0 (..., nx, nx), B = dx/du (..., nx, nu) by forward-mode tangents."""
        self._check(x0, u)
        lead, nx = x0.shape[:-1], self.nx
        x1, jac = self._with_tangents(x0.reshape(-1, nx), u.reshape(-1, self.nu), inputs_only=False)
        jac = jac.reshape(*lead, nx, nx + self.nu)
        return x1.reshape(*lead, nx), jac[..., :nx], jac[..., nx:]

    def step_with_input_jacobian(self, x0: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """x(tau) and B = dx/du (..., nx, nu) alone: nu tangents a sample where step_with_jacobian carries nx + nu,
        for callers that need no A (a cold solve's inputs node by node)."""
        self._check(x0, u)
        lead, nx = x0.shape[:-1], self.nx
        x1, jac = self._with_tangents(x0.reshape(-1, nx), u.reshape(-1, self.nu), inputs_only=True)
        return x1.reshape(*lead, nx), jac.reshape(*lead, nx, self.nu)

    def step_with_jacobian_plus(
        self, x0: np.ndarray, u: np.ndarray, x_plain: np.ndarray, u_plain: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """step_with_jacobian at x0, u (..., nx), (..., nu) and step at rows x_plain, u_plain (k, nx), (k, nu) in one
        pass: the plain rows join the values' GEMMs without tangents (the estimator's step beside the nodes)."""
        self._check(x0, u)
        self._check(x_plain, u_plain)
        lead, nx, nu = x0.shape[:-1], self.nx, self.nu
        x0, u = x0.reshape(-1, nx), u.reshape(-1, nu)
        batch = x0.shape[0]
        rows = np.concatenate((x0, x_plain)), np.concatenate((u, u_plain))
        x1, jac = self._with_tangents(*rows, inputs_only=False, plain=x_plain.shape[0])
        jac = jac.reshape(*lead, nx, nx + nu)
        return x1[:batch].reshape(*lead, nx), jac[..., :nx], jac[..., nx:], x1[batch:]

    def _with_tangents(
        self, x0: np.ndarray, u: np.ndarray, inputs_only: bool, plain: int = 0
    ) -> tuple[np.ndarray, np.ndarray]:
        """x(tau) (rows, nx) and its Jacobian (rows - plain, nx, k) w.r.t. (x0, u), or u alone, of rows x0, u; the
        last `plain` rows get values alone.

        Values and the k tangents ride together in one (rows + batch * k, width) matrix, the values in its first
        rows and the tangents below, so every layer is a single GEMM and the values and tangents are contiguous
        views of it: one call per layer instead of two.
        """
        nx, nu = self.nx, self.nu
        n_in = nu if inputs_only else nx + nu
        rows, width = x0.shape[0], self.b_in.shape[0]
        batch = rows - plain
        z = np.empty((rows + batch * n_in, width))
        value, tangent = z[:rows], z[rows:].reshape(batch, n_in, width)
        a, trig = self._first_layer(x0, u)
        y, slope = self.act(a)
        value[...] = y
        if plain:
            slope = slope[:batch]
            trig = None if trig is None else (trig[0][:batch], trig[1][:batch])
        if inputs_only:  # the periodic states' rows are x0's: u's rows are the plain first layer's
            np.multiply(slope[:, None, :], self.w_in[nx:], out=tangent)
        else:
            self._input_tangents(slope, self._angle_rows(trig), tangent)
        for w, b in self.hidden:
            z = z @ w
            value, tangent = z[:rows], z[rows:].reshape(batch, n_in, width)
            value += b
            y, slope = self.act(value)
            value[...] = y
            tangent *= slope[:batch, None, :]
        out = z @ self.w_out
        x1 = out[:rows]
        x1 += self.b_out
        jac = out[rows:].reshape(batch, n_in, nx).swapaxes(-1, -2)  # (batch, nx, n_in)
        if self.start is not None:
            prior_nu, alone = self.prior_nu, self.start.jacobian
            if alone is not None:  # the value of every row in one call (each call's code and data are fetched anew)
                x1 += self.start.value(x0, u[:, :prior_nu])[0]
                jp = alone(x0[:batch], u[:batch, :prior_nu])
            else:
                xp, jp = self.start.with_jacobian(x0[:batch], u[:batch, :prior_nu])
                x1[:batch] += xp
                if plain:
                    x1[batch:] += self.start.value(x0[batch:], u[batch:, :prior_nu])[0]
            jp = jp.reshape(batch, nx, nx + prior_nu)
            if inputs_only:
                jac[..., :prior_nu] += jp[..., nx:]
            else:
                jac[..., : nx + prior_nu] += jp
        elif self.hard_ic:
            x1 += x0
            if not inputs_only:
                jac[:, :, :nx] += self.eye
        return x1, jac


@dataclass
class SecondOrderNumpyFlow(NumpyFlow):
    """NumpyFlow of a second-order PINN: q(tau) = q0 + v0 tau + N_G, v(tau) = v0 + N_g + dN_G/dt (N_G, N_g: the
    network output summed over the gates with weights G_k(tau), g_k(tau)). Rows ride in two contiguous blocks,
    z[0] = the values and their (x0, u) tangents, z[1] = the time derivatives of those rows, so every layer is
    one GEMM and every elementwise update acts on a whole block; the output layer maps z[0] by [W_G, W_g] and
    adds z[1] @ W_G (the dN_G/dt term) to the velocity part."""

    t_in: np.ndarray = None  # (width,): d(first-layer pre-activation)/dt

    def __post_init__(self) -> None:
        super().__post_init__()
        self.nq = self.nx // 2
        self.w_time = np.ascontiguousarray(self.w_out[:, : self.nq])  # W_G: the time block's velocity increment
        self.full = partial(with_curvature, NUMPY, self.activation)
        self.kinematic = np.zeros((self.nx, self.nx + self.nu))  # d(q0 + v0 tau, v0)/d(x0, u)
        self.kinematic[:, : self.nx] = np.eye(self.nx)
        self.kinematic[: self.nq, self.nq : self.nx] = self.tau * np.eye(self.nq)

    @classmethod
    def from_second_order_pinn(
        cls, model: PINN, tau: float, facts: dict[str, object] | None = None
    ) -> SecondOrderNumpyFlow:
        """Fold the gate sums at t = tau into the output maps [W_G, W_g] (values) and W_G (time derivatives)."""
        facts = {**(facts or _facts(model, tau, (), ())), "tau": float(tau)}
        first, t_in = _folded_input(model, tau)
        t = torch.full((1,), float(tau), dtype=model.out_scale.dtype)
        w_big, b_big = _gate_sum(model, model.gate_integrals(t))
        w_g, b_g = _gate_sum(model, model.gates(t)[0])
        return cls(
            hidden=_hidden(model), w_out=np.hstack((w_big, w_g)), b_out=np.concatenate((b_big, b_g)), hard_ic=True,
            activation=model.config["activation"], nx=model.nx, nu=model.nu, t_in=t_in, **first, **facts,
        )  # fmt: skip

    def _propagate(self, z: np.ndarray) -> np.ndarray:
        """Carry z (2, batch, rows, width) through the hidden layers; row 0 is the value, rows 1: its tangents."""
        shape, width = z.shape, z.shape[-1]
        for w, b in self.hidden:
            z = (z.reshape(-1, width) @ w).reshape(shape)
            value = z[0, :, 0]
            value += b
            if shape[2] == 1:  # values only: d/dt of a value needs the slope, not the curvature
                y, slope = self.act(value)
            else:
                y, slope, bend = self.full(value)
                bend *= z[1, :, 0]  # sigma'' times the pre-activation's d/dt: the product rule's cross term
                bend = bend[:, None] * z[0, :, 1:]
            z[1] *= slope[:, None]
            if shape[2] > 1:
                z[1, :, 1:] += bend
                z[0, :, 1:] *= slope[:, None]
            value[...] = y
        return z

    def _output(self, z: np.ndarray) -> np.ndarray:
        """(batch, rows, nx): the state increment (row 0) and Jacobian columns of the network part."""
        _, batch, rows, width = z.shape
        out = z[0].reshape(-1, width) @ self.w_out
        out[:, self.nq :] += z[1].reshape(-1, width) @ self.w_time
        return out.reshape(batch, rows, self.nx)

    def _state(self, x0: np.ndarray, increment: np.ndarray) -> np.ndarray:
        """(q, v)(tau) = (q0 + v0 tau, v0) + the network's increment."""
        x1 = x0 + increment
        x1 += self.b_out
        x1[:, : self.nq] += self.tau * x0[:, self.nq :]
        return x1

    def step(self, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
        """x(tau) for x0 (..., nx), u (..., nu)."""
        self._check(x0, u)
        lead = x0.shape[:-1]
        x0, u = x0.reshape(-1, self.nx), u.reshape(-1, self.nu)
        batch, width = x0.shape[0], self.b_in.shape[0]
        y, slope = self.act(self._first_layer(x0, u)[0])
        z = np.empty((2, batch, 1, width))
        z[0, :, 0] = y
        np.multiply(slope, self.t_in, out=z[1, :, 0])
        increment = self._output(self._propagate(z))[:, 0]
        return self._state(x0, increment).reshape(*lead, self.nx)

    def step_with_jacobian(self, x0: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x(tau), A, B: per sample 1 + nx + nu rows [N, dN/dx_j] and their time derivatives, one GEMM a layer."""
        self._check(x0, u)
        lead, nx, n_in = x0.shape[:-1], self.nx, self.nx + self.nu
        x0, u = x0.reshape(-1, nx), u.reshape(-1, self.nu)
        batch, width = x0.shape[0], self.b_in.shape[0]
        z = np.empty((2, batch, 1 + n_in, width))
        a, trig = self._first_layer(x0, u)
        angle_rows = self._angle_rows(trig)
        y, slope, bend = self.full(a)
        z[0, :, 0] = y
        np.multiply(slope, self.t_in, out=z[1, :, 0])
        self._input_tangents(slope, angle_rows, z[0, :, 1:])
        bend *= self.t_in
        self._input_tangents(bend, angle_rows, z[1, :, 1:])
        out = self._output(self._propagate(z))
        x1 = self._state(x0, out[:, 0])
        jac = out[:, 1:].swapaxes(-1, -2)
        jac += self.kinematic
        jac = jac.reshape(*lead, nx, n_in)
        return x1.reshape(*lead, nx), jac[..., :nx], jac[..., nx:]

    def step_with_input_jacobian(self, x0: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """x(tau) and B: through step_with_jacobian (its time-derivative rows share the tangents' layout)."""
        x1, _, b = self.step_with_jacobian(x0, u)
        return x1, b

    def step_with_jacobian_plus(
        self, x0: np.ndarray, u: np.ndarray, x_plain: np.ndarray, u_plain: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """step_with_jacobian and step, in two passes: the rows here carry time derivatives too."""
        return (*self.step_with_jacobian(x0, u), self.step(x_plain, u_plain))
