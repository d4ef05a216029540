"""The trained network as plain numpy: batch-1 controller calls are dominated by per-op overhead,
which is several times lower in numpy than in torch. Same weights, same math as pinn.PINN."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from pinnmpc.pinn import PINN


def _tanh(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    y = np.tanh(a)
    slope = y * y
    np.subtract(1.0, slope, out=slope)
    return y, slope


def _sin(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.sin(a), np.cos(a)


def _silu(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    s = 1.0 / (1.0 + np.exp(-a))
    return a * s, s * (1.0 + a * (1.0 - s))


def _softplus(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.logaddexp(0.0, a), 1.0 / (1.0 + np.exp(-a))


def _silu_value(a: np.ndarray) -> np.ndarray:
    return a / (1.0 + np.exp(-a))


def _softplus_value(a: np.ndarray) -> np.ndarray:
    return np.logaddexp(0.0, a)


def _np(t: torch.Tensor) -> np.ndarray:
    """A float64 numpy copy, detached from the torch module."""
    return t.detach().double().numpy().copy()


NUMPY_ACTIVATIONS = {"tanh": _tanh, "sin": _sin, "silu": _silu, "softplus": _softplus}  # mirrors pinn.ACTIVATIONS
VALUE_ACTIVATIONS = {"tanh": np.tanh, "sin": np.sin, "silu": _silu_value, "softplus": _softplus_value}  # no slope


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

    def __post_init__(self) -> None:
        self.eye = np.eye(self.nx)  # dx/dx0 of the skip connection x0 + ...
        self.act = NUMPY_ACTIVATIONS[self.activation]
        self.value = VALUE_ACTIVATIONS[self.activation]

    @classmethod
    def from_pinn(cls, model: PINN, tau: float) -> NumpyFlow:
        """Copy float64 weights out of the torch module and fold in what is constant at t = tau."""
        layers = [(_np(m.weight), _np(m.bias)) for m in model.net.layers]
        center, half = _np(model.in_center), _np(model.in_half)
        w1, b1 = layers[0]
        w_in = w1[:, 1:] / half[1:]
        b_in = b1 + w1[:, 0] * (tau - center[0]) / half[0] - w_in @ center[1:]
        w, b = layers[-1]
        scale = _np(model.out_scale)
        hard = model.exact_ic
        if hard:  # the time gates are constants at t = tau: x(tau) - x0 = scale * sum_k g_k N_k
            g = _np(model.gates(torch.full((1,), float(tau), dtype=model.out_scale.dtype))[0])
            heads = (model.n_gates, model.nx)
            w, b = np.einsum("k,kij->ij", g, w.reshape(*heads, -1)), g @ b.reshape(heads)
            w_out, b_out = (scale[:, None] * w).T, scale * b
        else:
            w_out, b_out = (scale[:, None] * w).T, scale * b + _np(model.out_center)
        hidden = [(np.ascontiguousarray(wh.T), bh) for wh, bh in layers[1:-1]]
        return cls(
            np.ascontiguousarray(w_in.T), b_in, hidden, np.ascontiguousarray(w_out), b_out, hard,
            model.config["activation"], model.nx, model.nu,
        )  # fmt: skip

    def _first_layer(self, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Pre-activation of the first layer; two GEMMs instead of a concatenation and one."""
        a = x0 @ self.w_in[: self.nx]
        a += u @ self.w_in[self.nx :]
        a += self.b_in
        return a

    def step(self, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
        """x(tau) for x0 (..., nx), u (..., nu)."""
        z = self.value(self._first_layer(x0, u))
        for w, b in self.hidden:
            z = self.value(z @ w + b)
        n = z @ self.w_out + self.b_out
        return x0 + n if self.hard_ic else n

    def step_with_jacobian(self, x0: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x(tau), A = dx/dx0 (..., nx, nx), B = dx/du (..., nx, nu) by forward-mode tangents.

        Values and the nx + nu tangents ride together in one (batch * (1 + nx + nu), width) matrix, the
        batch's values in its first rows and their tangents below, so every layer is a single GEMM and
        the values and tangents are contiguous views of it: at batch 1-5 that is ~30% faster than two.
        """
        lead, nx, n_in = x0.shape[:-1], self.nx, self.nx + self.nu
        x0, u = x0.reshape(-1, nx), u.reshape(-1, self.nu)
        batch, width = x0.shape[0], self.b_in.shape[0]
        z = np.empty((batch * (1 + n_in), width))
        value, tangent = z[:batch], z[batch:].reshape(batch, n_in, width)
        y, slope = self.act(self._first_layer(x0, u))
        value[...] = y
        np.multiply(slope[:, None, :], self.w_in, out=tangent)
        for w, b in self.hidden:
            z = z @ w
            value, tangent = z[:batch], z[batch:].reshape(batch, n_in, width)
            value += b
            y, slope = self.act(value)
            value[...] = y
            tangent *= slope[:, None, :]
        out = z @ self.w_out
        x1 = out[:batch]
        x1 += self.b_out
        jac = out[batch:].reshape(batch, n_in, nx).swapaxes(-1, -2)  # (batch, nx, n_in)
        if self.hard_ic:
            x1 += x0
            jac[:, :, :nx] += self.eye
        jac = jac.reshape(*lead, nx, n_in)
        return x1.reshape(*lead, nx), jac[..., :nx], jac[..., nx:]
