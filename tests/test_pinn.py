"""The network: exact initial condition, forward-mode derivatives checked against finite differences."""

from __future__ import annotations

import math

import pytest
import torch

from pinnmpc.pinn import ACTIVATIONS, PINN
from pinnmpc.systems import PowerCube

BOX = dict(
    state_low=[-math.pi, -math.pi, -2.5, -2.5],
    state_high=[math.pi, math.pi, 2.5, 2.5],
    input_low=[-0.5, -0.5],
    input_high=[0.5, 0.5],
    t_max=0.25,
)


def _points(n: int = 16, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    t = torch.rand(n, 1, generator=g, dtype=torch.float64) * 0.25
    x0 = (torch.rand(n, 4, generator=g, dtype=torch.float64) * 2 - 1) * torch.tensor([3.0, 3.0, 2.5, 2.5])
    u = torch.rand(n, 2, generator=g, dtype=torch.float64) - 0.5
    return t, x0, u


@pytest.mark.parametrize("ic", ["hard", "soft"])
@pytest.mark.parametrize("activation", sorted(ACTIVATIONS))
def test_time_derivative_matches_finite_difference(ic, activation):
    torch.manual_seed(0)
    model = PINN(**BOX, hidden=[16, 16], activation=activation, ic=ic, output_scale=[0.6, 0.6, 5.0, 5.0]).double()
    t, x0, u = _points()
    x, dxdt = model.with_time_derivative(t, x0, u)
    eps = 1e-6
    fd = (model(t + eps, x0, u) - model(t - eps, x0, u)) / (2 * eps)
    assert torch.allclose(x, model(t, x0, u), atol=1e-14)
    assert (dxdt - fd).abs().max() < 1e-7


def test_physics_residual_matches_finite_difference_residual():
    torch.manual_seed(1)
    model = PINN(**BOX, hidden=[32, 32], output_scale=[0.6, 0.6, 5.0, 5.0]).double()
    system = PowerCube()
    t, x0, u = _points(seed=3)
    x, dxdt = model.with_time_derivative(t, x0, u)
    eps = 1e-6
    fd = (model(t + eps, x0, u) - model(t - eps, x0, u)) / (2 * eps)
    for form in ("explicit", "mass"):
        assert torch.allclose(system.residual(x, dxdt, u, form), system.residual(x, fd, u, form), atol=1e-5)


@pytest.mark.parametrize("ic", ["hard", "soft"])
def test_jacobian_matches_autograd(ic):
    torch.manual_seed(2)
    model = PINN(**BOX, hidden=[16, 16], ic=ic).double()
    t, x0, u = _points(5)
    _, jac = model.with_jacobian(t, x0, u)
    ref = torch.func.vmap(torch.func.jacrev(model, argnums=(1, 2)))(t, x0, u)
    assert (jac - torch.cat(ref, dim=-1)).abs().max() < 1e-12


def test_hard_initial_condition_is_exact():
    model = PINN(**BOX, hidden=[8], output_scale=[1.0, 1.0, 1.0, 1.0]).double()
    _, x0, u = _points()
    assert torch.equal(model(torch.zeros(len(x0), 1, dtype=torch.float64), x0, u), x0)


def test_bad_configuration_is_named():
    with pytest.raises(ValueError, match="unknown activation 'relu'"):
        PINN(**BOX, activation="relu")
    with pytest.raises(ValueError, match="initial-condition mode 'exact'"):
        PINN(**BOX, ic="exact")
    with pytest.raises(ValueError, match="output_scale must be 4 positive"):
        PINN(**BOX, output_scale=[1.0, -1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match="hidden layer widths"):
        PINN(**BOX, hidden=[])
    with pytest.raises(ValueError, match="t_max must be > 0"):
        PINN(**{**BOX, "t_max": 0.0})
