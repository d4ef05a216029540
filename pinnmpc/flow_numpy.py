"""The trained network as plain numpy: batch-1 controller calls are dominated by per-op overhead,
which is several times lower in numpy than in torch. Same weights, same math as pinn.PINN."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from pinnmpc.pinn import PINN


def _tanh(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    y = np.tanh(a)
    return y, 1.0 - y * y


def _sin(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.sin(a), np.cos(a)


def _silu(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    s = 1.0 / (1.0 + np.exp(-a))
    return a * s, s * (1.0 + a * (1.0 - s))


def _softplus(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.logaddexp(0.0, a), 1.0 / (1.0 + np.exp(-a))


def _np(t: torch.Tensor) -> np.ndarray:
    """A float64 numpy copy, detached from the torch module."""
    return t.detach().double().numpy().copy()


NUMPY_ACTIVATIONS = {"tanh": _tanh, "sin": _sin, "silu": _silu, "softplus": _softplus}  # mirrors pinn.ACTIVATIONS


@dataclass
class NumpyFlow:
    """x(tau) and its Jacobian w.r.t. (x0, u) for a fixed tau, with the input normalisation folded into layer 1."""

    w_first: np.ndarray  # (width, nx + nu): first layer acting on raw (x0, u)
    b_first: np.ndarray  # (width,): first-layer bias with t = tau and the normalisation folded in
    hidden: list[tuple[np.ndarray, np.ndarray]]  # remaining layers (W, b), the last one linear
    gain: np.ndarray  # (nx,): multiplies the network output (hard IC: tau / t_max * scale)
    offset: np.ndarray  # (nx,): added to it for the soft IC (output centre); 0 for hard IC
    hard_ic: bool
    activation: str
    nx: int
    nu: int

    def __post_init__(self) -> None:
        self.eye = np.eye(self.nx)  # dx/dx0 of the skip connection x0 + ...

    @classmethod
    def from_pinn(cls, model: PINN, tau: float) -> NumpyFlow:
        """Copy float64 weights out of the torch module and fold in what is constant at t = tau."""
        layers = [(_np(m.weight), _np(m.bias)) for m in model.net.layers]
        center, half = _np(model.in_center), _np(model.in_half)
        w1, b1 = layers[0]
        w_first = w1[:, 1:] / half[1:]
        b_first = b1 + w1[:, 0] * (tau - center[0]) / half[0] - w_first @ center[1:]
        scale = _np(model.out_scale)
        hard = model.ic == "hard"
        gain = scale * (tau / model.t_max) if hard else scale
        offset = np.zeros(model.nx) if hard else _np(model.out_center)
        return cls(w_first, b_first, layers[1:], gain, offset, hard, model.config["activation"], model.nx, model.nu)

    def step(self, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
        """x(tau) for x0 (..., nx), u (..., nu)."""
        act = NUMPY_ACTIVATIONS[self.activation]
        z = act(np.concatenate((x0, u), -1) @ self.w_first.T + self.b_first)[0]
        for w, b in self.hidden[:-1]:
            z = act(z @ w.T + b)[0]
        w, b = self.hidden[-1]
        n = (z @ w.T + b) * self.gain
        return x0 + n if self.hard_ic else n + self.offset

    def step_with_jacobian(self, x0: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x(tau), A = dx/dx0 (..., nx, nx), B = dx/du (..., nx, nu) by forward-mode tangents.

        Tangents are kept tangent-major, (batch * (nx + nu), width), so every layer is one GEMM.
        """
        act = NUMPY_ACTIVATIONS[self.activation]
        lead = x0.shape[:-1]
        n_in = self.nx + self.nu
        z, slope = act(np.concatenate((x0, u), -1).reshape(-1, n_in) @ self.w_first.T + self.b_first)
        width = z.shape[-1]
        dz = (slope[:, None, :] * self.w_first.T).reshape(-1, width)  # (batch * n_in, width)
        for w, b in self.hidden[:-1]:
            z, slope = act(z @ w.T + b)
            dz = (dz @ w.T).reshape(-1, n_in, width)
            dz = (dz * slope[:, None, :]).reshape(-1, width)
        w, b = self.hidden[-1]
        n = (z @ w.T + b) * self.gain
        jac = ((dz @ w.T) * self.gain).reshape(-1, n_in, self.nx).swapaxes(-1, -2)  # (batch, nx, n_in)
        if self.hard_ic:
            x1 = x0.reshape(-1, self.nx) + n
            jac[:, :, : self.nx] += self.eye
        else:
            x1 = n + self.offset
        jac = jac.reshape(*lead, self.nx, n_in)
        return x1.reshape(*lead, self.nx), jac[..., : self.nx], jac[..., self.nx :]
