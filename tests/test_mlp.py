"""The MLP's passes, written once over an array library, agree across torch, numpy and CasADi, and their
tangents are the derivatives of their values."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
import torch

from pinnmpc.surrogate import mlp
from pinnmpc.surrogate.activations import NUMPY, TANGENTS, check_activation
from pinnmpc.surrogate.casadi_network import CASADI
from pinnmpc.surrogate.network import TangentMLP

N_IN, N_OUT, BATCH, K = 5, 3, 7, 4


def _net(activation: str) -> TangentMLP:
    """A seeded float64 MLP with non-zero biases, so that no term of a pass vanishes by accident."""
    torch.manual_seed(0)
    net = TangentMLP(N_IN, N_OUT, [12, 9], activation).double()
    with torch.no_grad():
        for layer in net.layers:
            layer.bias.normal_(0.0, 0.5)
    return net


def _numpy_layers(net: TangentMLP) -> list[tuple[np.ndarray, np.ndarray]]:
    """The same layers as numpy keeps them: W transposed."""
    return [(w.detach().numpy().T.copy(), b.detach().numpy().copy()) for w, b in net.pairs()]


@pytest.mark.parametrize("activation", sorted(TANGENTS))
def test_numpy_passes_equal_the_torch_module(activation: str) -> None:
    """value, tangent, second and mixed passes give the module's numbers in numpy too."""
    net, rng = _net(activation), np.random.default_rng(1)
    z, dz, dt = rng.normal(size=(BATCH, N_IN)), rng.normal(size=(BATCH, K, N_IN)), rng.normal(size=(BATCH, N_IN))
    layers = _numpy_layers(net)
    tz, tdz, tdt = (torch.from_numpy(a) for a in (z, dz, dt))
    with torch.no_grad():
        pairs = [
            (mlp.value(NUMPY, layers, activation, z), net(tz)),
            (mlp.tangent(NUMPY, layers, activation, z, dz), net.forward_tangent(tz, tdz)),
            (mlp.second(NUMPY, layers, activation, z, dt), net.forward_second(tz, tdt)),
            (mlp.mixed(NUMPY, layers, activation, z, dt, dz), net.forward_mixed(tz, tdt, tdz)),
        ]
    for ours, theirs in pairs:
        ours, theirs = (v if isinstance(v, tuple) else (v,) for v in (ours, theirs))
        assert len(ours) == len(theirs)
        for a, b in zip(ours, theirs):
            np.testing.assert_allclose(a, b.numpy(), rtol=1e-12, atol=1e-13)


@pytest.mark.parametrize("activation", sorted(TANGENTS))
def test_tangents_and_curvatures_are_the_derivatives_of_the_values(activation: str) -> None:
    """Central differences of the value pass match the tangent pass, and of the tangent the second pass."""
    net, rng = _net(activation), np.random.default_rng(2)
    layers = _numpy_layers(net)
    z, d = rng.normal(size=N_IN), rng.normal(size=N_IN)
    h = 1e-5
    _, slope = mlp.tangent(NUMPY, layers, activation, z, d[None])
    _, first, curvature = mlp.second(NUMPY, layers, activation, z, d)
    plus, minus = (mlp.value(NUMPY, layers, activation, z + s * h * d) for s in (1, -1))
    centre = mlp.value(NUMPY, layers, activation, z)
    np.testing.assert_allclose(slope[0], (plus - minus) / (2 * h), rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(first, slope[0], rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(curvature, (plus - 2 * centre + minus) / h**2, rtol=1e-3, atol=1e-4)


@pytest.mark.parametrize("activation", sorted(TANGENTS))
def test_casadi_form_and_its_jacobian_equal_the_numpy_passes(activation: str) -> None:
    """The CasADi value pass (what the export writes) and CasADi's own Jacobian of it match numpy's passes."""
    net, rng = _net(activation), np.random.default_rng(3)
    layers = _numpy_layers(net)
    sym = ca.MX.sym("z", N_IN)
    columns = [(ca.DM(w.T), b) for w, b in layers]
    out = mlp.value(CASADI, columns, activation, sym)
    f = ca.Function("f", [sym], [out, ca.jacobian(out, sym)])
    z = rng.normal(size=N_IN)
    y, jac = (np.asarray(v) for v in f(z))
    value, tangents = mlp.tangent(NUMPY, layers, activation, z, np.eye(N_IN))
    np.testing.assert_allclose(y.ravel(), value, rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(jac, tangents.T, rtol=1e-12, atol=1e-13)


def test_an_unknown_activation_is_one_line_naming_the_choices() -> None:
    """A typo in model.activation names what exists."""
    expected = r"unknown activation 'relu'; expected one of \['silu', 'sin', 'softplus', 'tanh'\]"
    with pytest.raises(ValueError, match=expected):
        check_activation("relu")
    with pytest.raises(ValueError, match="unknown activation"):
        TangentMLP(2, 1, [4], "relu")
