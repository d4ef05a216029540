"""The network: exact initial condition, time gates, forward-mode derivatives checked against finite differences,
and the numpy fast path checked against torch."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pinnmpc.surrogate.activations import TANGENTS as ACTIVATIONS
from pinnmpc.surrogate.network import PINN
from pinnmpc.surrogate.numpy_flow import BlockDiagonal, NumpyFlow
from pinnmpc.surrogate.staged import StagedPINN
from pinnmpc.systems import PowerCube

BOX = dict(
    state_low=[-math.pi, -math.pi, -2.5, -2.5],
    state_high=[math.pi, math.pi, 2.5, 2.5],
    input_low=[-0.5, -0.5],
    input_high=[0.5, 0.5],
    t_max=0.25,
)

VARIANTS = {  # output structures: the paper's soft IC, x0 + t N, and x0 + t N_0 + sum_k (1 - exp(-t/T_k)) N_k
    "soft": {"ic": "soft"},
    "hard": {"ic": "hard"},
    "gated": {"ic": "gated", "time_basis": [0.02, 0.045]},
    "second-order hard": {"ic": "hard", "second_order": True},  # q = q0 + v0 t + G(t) N, v = dq/dt
    "second-order gated": {"ic": "gated", "time_basis": [0.02, 0.045], "second_order": True},
    "periodic gated": {"ic": "gated", "time_basis": [0.02, 0.045], "periodic": [0, 1]},  # angles as (sin, cos)
    "periodic second-order": {"ic": "gated", "time_basis": [0.02], "second_order": True, "periodic": [1]},
    "periodic soft": {"ic": "soft", "periodic": [0]},
    "angle sums gated": {"ic": "gated", "time_basis": [0.02], "periodic": [0, 1], "angle_sums": [[0, 1]]},
    "angle sums second-order": {
        "ic": "gated",
        "time_basis": [0.02],
        "second_order": True,
        "periodic": [0, 1],
        "angle_sums": [[1, 0]],
    },  # fmt: skip
}


def _points(n: int = 16, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    t = torch.rand(n, 1, generator=g, dtype=torch.float64) * 0.25
    x0 = (torch.rand(n, 4, generator=g, dtype=torch.float64) * 2 - 1) * torch.tensor([3.0, 3.0, 2.5, 2.5])
    u = torch.rand(n, 2, generator=g, dtype=torch.float64) - 0.5
    return t, x0, u


@pytest.mark.parametrize("variant", sorted(VARIANTS))
@pytest.mark.parametrize("activation", sorted(ACTIVATIONS))
def test_time_derivative_matches_finite_difference(variant, activation):
    torch.manual_seed(0)
    kw = VARIANTS[variant]
    model = PINN(**BOX, hidden=[16, 16], activation=activation, output_scale=[0.6, 0.6, 5.0, 5.0], **kw).double()
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


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_jacobian_matches_autograd(variant):
    torch.manual_seed(2)
    model = PINN(**BOX, hidden=[16, 16], **VARIANTS[variant]).double()
    t, x0, u = _points(5)
    _, jac = model.with_jacobian(t, x0, u)
    ref = torch.func.vmap(torch.func.jacrev(model, argnums=(1, 2)))(t, x0, u)
    assert (jac - torch.cat(ref, dim=-1)).abs().max() < 1e-12


@pytest.mark.parametrize("second_order", [False, True])
@pytest.mark.parametrize(("ic", "time_basis"), [("hard", []), ("gated", [0.01, 0.05])])
def test_hard_initial_condition_is_exact(ic, time_basis, second_order):
    kw = dict(ic=ic, time_basis=time_basis, second_order=second_order)
    model = PINN(**BOX, hidden=[8], output_scale=[1.0, 1.0, 1.0, 1.0], **kw).double()
    _, x0, u = _points()
    assert torch.equal(model(torch.zeros(len(x0), 1, dtype=torch.float64), x0, u), x0)


@pytest.mark.parametrize("variant", ["second-order hard", "second-order gated"])
def test_second_order_velocity_is_the_position_derivative(variant):
    torch.manual_seed(6)
    model = PINN(**BOX, hidden=[16, 16], output_scale=[0.3, 0.4, 3.0, 3.5], **VARIANTS[variant]).double()
    t, x0, u = _points(seed=8)
    x, dxdt = model.with_time_derivative(t, x0, u)
    assert torch.equal(dxdt[:, :2], x[:, 2:])  # dq/dt = v by construction, not by training
    residual = PowerCube().residual(x, dxdt, u, "explicit")
    assert torch.equal(residual[:, :2], torch.zeros_like(residual[:, :2]))  # only the dynamics are left to learn
    assert residual[:, 2:].abs().min() > 0
    eps = 1e-6
    fd = (model(t + eps, x0, u)[:, :2] - model(t - eps, x0, u)[:, :2]) / (2 * eps)
    assert (fd - x[:, 2:]).abs().max() < 1e-7
    assert model.net.layers[-1].out_features == 2 * model.n_gates  # one head per gate for the 2 positions only


@pytest.mark.parametrize("variant", ["periodic gated", "periodic second-order", "angle sums second-order"])
def test_periodic_states_give_a_periodic_flow(variant):
    torch.manual_seed(9)
    model = PINN(**BOX, hidden=[16, 16], output_scale=[0.3, 0.4, 3.0, 3.5], **VARIANTS[variant]).double()
    t, x0, u = _points(seed=10)
    turn = torch.zeros(4, dtype=torch.float64)
    turn[model.periodic] = 2 * math.pi  # a full turn of every periodic joint, leaving the box
    torch.testing.assert_close(model(t, x0 + turn, u) - turn, model(t, x0, u), rtol=0, atol=1e-12)
    other = torch.tensor([0.0, 0.0, 0.1, 0.0], dtype=torch.float64)  # velocities are not periodic
    assert (model(t, x0 + other, u) - model(t, x0, u) - other).abs().max() > 1e-6
    n_in = model.net.layers[0].in_features
    n_sums = len(model.config["angle_sums"])
    assert n_in == 7 + len(model.periodic) + 2 * n_sums  # an extra cosine per periodic state, (sin, cos) per sum


def test_time_gates_start_at_zero_and_relax():
    model = PINN(**BOX, hidden=[8], ic="gated", time_basis=[0.02, 0.045]).double()
    t = torch.tensor([[0.0], [0.02], [0.25]], dtype=torch.float64)
    g, dg = model.gates(t)
    assert model.n_gates == 3 and g.shape == (3, 3)
    assert torch.equal(g[0], torch.zeros(3))  # every gate vanishes at t = 0: x(0) = x0 for any network
    torch.testing.assert_close(g[:, 0], t[:, 0] / 0.25)  # g_0 = t / t_max
    torch.testing.assert_close(g[1, 1], torch.tensor(1 - math.exp(-1), dtype=torch.float64))  # 1 - 1/e at t = T
    torch.testing.assert_close(dg[0], torch.tensor([1 / 0.25, 1 / 0.02, 1 / 0.045], dtype=torch.float64))
    eps = 1e-7
    torch.testing.assert_close(dg, (model.gates(t + eps)[0] - model.gates(t - eps)[0]) / (2 * eps), atol=1e-6, rtol=0)


@pytest.mark.parametrize("variant", sorted(VARIANTS))
@pytest.mark.parametrize("lead", [(1,), (3, 5)])
@pytest.mark.parametrize("activation", ["tanh", "silu"])  # silu: the numpy path's fused second-order form
def test_numpy_flow_matches_torch(variant, lead, activation):
    torch.manual_seed(4)
    scale = [0.3, 0.4, 3.0, 3.5]
    model = PINN(**BOX, hidden=[16, 16, 16], output_scale=scale, activation=activation, **VARIANTS[variant]).double()
    g = torch.Generator().manual_seed(5)
    x0 = (torch.rand(*lead, 4, generator=g, dtype=torch.float64) * 2 - 1) * 2.5
    u = torch.rand(*lead, 2, generator=g, dtype=torch.float64) - 0.5
    tau = 0.2
    x_ref, jac_ref = model.with_jacobian(torch.full((*lead, 1), tau, dtype=torch.float64), x0, u)
    flow = NumpyFlow.from_pinn(model, tau)
    x1, a, b = flow.step_with_jacobian(x0.numpy(), u.numpy())
    np.testing.assert_allclose(x1, x_ref.detach().numpy(), rtol=0, atol=1e-13)
    np.testing.assert_allclose(np.concatenate((a, b), -1), jac_ref.detach().numpy(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(flow.step(x0.numpy(), u.numpy()), x1, rtol=0, atol=1e-14)


def test_bad_configuration_is_named():
    with pytest.raises(ValueError, match="unknown activation 'relu'"):
        PINN(**BOX, activation="relu")
    with pytest.raises(ValueError, match="initial-condition mode 'exact'"):
        PINN(**BOX, ic="exact")
    with pytest.raises(ValueError, match="output_scale must be 4 positive"):
        PINN(**BOX, output_scale=[1.0, -1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match="hidden layer widths"):
        PINN(**BOX, hidden=[])
    with pytest.raises(ValueError, match="second_order=True needs an exact initial condition.*ic='soft'"):
        PINN(**BOX, ic="soft", second_order=True)
    odd = {**BOX, "state_low": [-1.0, -1.0, -1.0], "state_high": [1.0, 1.0, 1.0]}
    with pytest.raises(ValueError, match="state dimension 3"):
        PINN(**odd, second_order=True)
    with pytest.raises(ValueError, match=r"periodic must list distinct state indices in \[0, 4\), got \[0, 4\]"):
        PINN(**BOX, periodic=[0, 4])
    with pytest.raises(ValueError, match=r"distinct state indices.*got \[1, 1\]"):
        PINN(**BOX, periodic=[1, 1])
    with pytest.raises(ValueError, match=r"sums of two or more distinct periodic state indices \[0\]"):
        PINN(**BOX, periodic=[0], angle_sums=[[0, 1]])  # state 1 is not periodic
    with pytest.raises(ValueError, match=r"angle_sums must list sums of two or more.*got \[\[0\]\]"):
        PINN(**BOX, periodic=[0, 1], angle_sums=[[0]])
    with pytest.raises(ValueError, match=r"angle_sums lists a sum twice: \[\[0, 1\], \[0, 1\]\]"):
        PINN(**BOX, periodic=[0, 1], angle_sums=[[0, 1], [1, 0]])
    with pytest.raises(ValueError, match="t_max must be > 0"):
        PINN(**{**BOX, "t_max": 0.0})
    with pytest.raises(ValueError, match=r"time_basis must hold positive relaxation times in s, got \[0.02, -1.0\]"):
        PINN(**BOX, ic="gated", time_basis=[0.02, -1.0])
    with pytest.raises(ValueError, match="ic='gated' needs a non-empty time_basis"):
        PINN(**BOX, ic="soft", time_basis=[0.02])
    with pytest.raises(ValueError, match="ic='gated' needs a non-empty time_basis"):
        PINN(**BOX, ic="gated")


@pytest.mark.parametrize("name", ["gated", "periodic second-order", "hard"])
def test_merged_staged_network_is_exactly_base_plus_correction(name):
    torch.manual_seed(3)
    base = {**BOX, **VARIANTS[name], "hidden": [16, 16, 16], "activation": "silu", "output_scale": [0.3, 0.4, 2, 3]}
    correction = {**base, "hidden": [8, 12, 4], "output_scale": [1e-3, 2e-3, 1e-2, 3e-2]}
    staged = StagedPINN(base, correction, residual_level=0.05).double()
    with torch.no_grad():
        staged.correction.net.layers[-1].weight.mul_(10.0)  # a correction that matters
    merged = staged.merged()
    assert merged.config["hidden"] == [24, 28, 20]
    t, x0, u = _points(32, seed=4)
    x_staged = staged(t, x0, u)
    assert (x_staged - staged.base(t, x0, u)).abs().max() > 1e-4
    torch.testing.assert_close(merged(t, x0, u), x_staged, rtol=0, atol=1e-12)
    for got, want in zip(merged.with_time_derivative(t, x0, u), staged.with_time_derivative(t, x0, u)):
        torch.testing.assert_close(got, want, rtol=0, atol=1e-11)
    torch.testing.assert_close(merged(torch.zeros_like(t), x0, u), x0, rtol=0, atol=1e-12)  # still exact at t = 0
    assert not any(p.requires_grad for p in staged.base.parameters())


@pytest.mark.parametrize(
    ("change", "match"),
    [({"activation": "tanh"}, "differs in \\['activation'\\]"), ({"hidden": [8, 8]}, "differs in \\['depth'\\]")],
)
def test_correction_that_cannot_merge_is_refused(change, match):
    base = {**BOX, **VARIANTS["gated"], "hidden": [16, 16, 16], "activation": "silu"}
    with pytest.raises(ValueError, match=match):
        StagedPINN(base, {**base, **change}, residual_level=0.05)


@pytest.mark.parametrize("variant", ["periodic gated", "periodic second-order"])
@pytest.mark.parametrize("lead", [(1,), (3, 5)])
def test_numpy_flow_of_a_merged_network_multiplies_block_by_block_and_matches_torch(variant, lead):
    torch.manual_seed(6)
    base = {
        **BOX,
        **VARIANTS[variant],
        "hidden": [16, 16, 16],
        "activation": "silu",
        "output_scale": [0.3, 0.4, 3, 3.5],
    }
    staged = StagedPINN(base, {**base, "hidden": [8, 8, 8], "output_scale": [0.01] * 4}, residual_level=0.05)
    merged = staged.double().merged()
    flow = NumpyFlow.from_pinn(merged, 0.2)
    assert all(isinstance(w, BlockDiagonal) and len(w.blocks) == 2 for w, _ in flow.hidden)
    g = torch.Generator().manual_seed(7)
    x0 = (torch.rand(*lead, 4, generator=g, dtype=torch.float64) * 2 - 1) * 2.5
    u = torch.rand(*lead, 2, generator=g, dtype=torch.float64) - 0.5
    x_ref, jac_ref = merged.with_jacobian(torch.full((*lead, 1), 0.2, dtype=torch.float64), x0, u)
    x1, a, b = flow.step_with_jacobian(x0.numpy(), u.numpy())
    np.testing.assert_allclose(x1, x_ref.detach().numpy(), rtol=0, atol=1e-13)
    np.testing.assert_allclose(np.concatenate((a, b), -1), jac_ref.detach().numpy(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(flow.step(x0.numpy(), u.numpy()), x1, rtol=0, atol=1e-14)


def test_block_split_finds_the_blocks_and_leaves_dense_layers_alone():
    rng = np.random.default_rng(0)
    a, b, c = rng.normal(size=(3, 3)), rng.normal(size=(2, 2)), rng.normal(size=(4, 4))
    w = np.zeros((9, 9))
    w[:3, :3], w[3:5, 3:5], w[5:, 5:] = a, b, c
    split = BlockDiagonal.split(w)
    assert [blk.shape for blk in split.blocks] == [(3, 3), (2, 2), (4, 4)]
    z = rng.normal(size=(2, 5, 9))
    np.testing.assert_allclose(z @ split, z @ w, rtol=0, atol=1e-14)
    dense = rng.normal(size=(9, 9))
    assert BlockDiagonal.split(dense) is dense
