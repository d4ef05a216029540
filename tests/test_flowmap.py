"""One contract for every flow map (pinnmpc.surrogate.flowmap.FlowMap): the surrogate, its numpy fast path and the
true model by RK4 in torch and as compiled C, on the PowerCube and on the planar 3-link arm, each put through the
same checks."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import casadi as ca
import numpy as np
import pytest
import torch

from pinnmpc.controller.ocp import HorizonOCP
from pinnmpc.surrogate import Surrogate, load_surrogate
from pinnmpc.surrogate.flowmap import CompiledRK4, ExactValues, FlowMap, RK4Model, check_flow_map, numpy_path
from pinnmpc.surrogate.network import PINN
from pinnmpc.surrogate.numpy_flow import NumpyFlow
from pinnmpc.surrogate.previous_input import PreviousInputFlow
from pinnmpc.systems import load_system
from pinnmpc.systems.base import System
from pinnmpc.systems.compiled import BatchedFunction

SYSTEMS = ("powercube", "planar3")
KINDS = ("surrogate", "numpy", "rk4_torch", "rk4_compiled")
SLOW = {("planar3", "rk4_torch")}  # autodiff through 40 RK4 steps of the URDF arm's torch rhs: the slow case
CASES = [
    pytest.param(name, kind, id=f"{name}-{kind}", marks=[pytest.mark.slow] if (name, kind) in SLOW else [])
    for name in SYSTEMS
    for kind in KINDS
]
FD_EPS = 1e-6  # central-difference step on inputs scaled to O(1)
RK4_H = {"powercube": 0.02, "planar3": 0.0025}  # stable RK4 steps of the true-model maps, s


@pytest.fixture(scope="module")
def systems() -> dict[str, System]:
    return {name: load_system(name) for name in SYSTEMS}


def _planar3_surrogate(system: System) -> Surrogate:
    """A small untrained second-order PINN for the planar arm's boxes (weights seeded): a contract needs no
    training, and second order with periodic angles and their sums takes the numpy path's most involved branch."""
    torch.manual_seed(0)
    box, ubox = system.state_box, system.input_box
    model = PINN(
        box.low, box.high, ubox.low, ubox.high, t_max=0.125, hidden=[16, 16], activation="silu", ic="gated",
        time_basis=[0.004, 0.05], second_order=True, periodic=[0, 1, 2], angle_sums=[[0, 1], [0, 1, 2], [1, 2]],
    )  # fmt: skip
    return Surrogate(model, system.tau, system.state_names, system.input_names)


@pytest.fixture(scope="module")
def maps(systems: dict[str, System]) -> dict[tuple[str, str], FlowMap]:
    """Every implementation for every system; the PowerCube's surrogate is the shipped network."""
    out: dict[tuple[str, str], FlowMap] = {}
    for name, system in systems.items():
        surrogate = load_surrogate() if name == "powercube" else _planar3_surrogate(system)
        h = RK4_H[name]
        out[name, "surrogate"] = surrogate
        out[name, "numpy"] = surrogate.numpy_flow()
        out[name, "rk4_torch"] = RK4Model(system, system.tau, h)
        out[name, "rk4_compiled"] = CompiledRK4(system, system.tau, h)
    return out


def _points(system: System, lead: tuple[int, ...], seed: int) -> tuple[np.ndarray, np.ndarray]:
    """States and inputs in the middle of the boxes, velocities away from zero (the Coulomb tanh is steep there)."""
    rng = np.random.default_rng(seed)
    lo, hi = np.array(system.state_box.low), np.array(system.state_box.high)
    x = rng.uniform(0.5 * lo, 0.5 * hi, (*lead, len(lo)))
    nq = system.nq
    x[..., nq:] = np.sign(x[..., nq:]) * np.maximum(np.abs(x[..., nq:]), 0.2)
    ulo, uhi = np.array(system.input_box.low), np.array(system.input_box.high)
    return x, rng.uniform(0.3 * ulo, 0.3 * uhi, (*lead, len(ulo)))


def _caller(model: FlowMap) -> Callable[..., Any]:
    """Call a method of the map with numpy arrays in and float64 numpy arrays out, whatever its array_api."""

    def call(method: str, x: np.ndarray, u: np.ndarray) -> Any:
        if model.array_api == "torch":
            out = getattr(model, method)(torch.from_numpy(x), torch.from_numpy(u))
            return tuple(o.detach().numpy() for o in out) if isinstance(out, tuple) else out.detach().numpy()
        return getattr(model, method)(x, u)

    return call


@pytest.mark.parametrize(("name", "kind"), CASES)
def test_facts_and_boxes(maps: dict, systems: dict, name: str, kind: str) -> None:
    model, system = maps[name, kind], systems[name]
    assert isinstance(model, FlowMap)
    check_flow_map(model)
    assert model.array_api in ("torch", "numpy")
    assert model.tau == pytest.approx(system.tau, rel=0, abs=1e-15)
    assert (model.nx, model.nu) == (len(system.state_names), len(system.input_names))
    assert tuple(model.state_names) == tuple(system.state_names)
    assert tuple(model.input_names) == tuple(system.input_names)
    assert model.state_box.dim == model.nx and model.input_box.dim == model.nu
    if kind.startswith("rk4"):  # the physics: the system's own boxes
        assert (model.state_box, model.input_box) == (system.state_box, system.input_box)
    else:  # a network: its training box, the same in torch and numpy
        assert model.state_box == maps[name, "surrogate"].state_box
        assert model.input_box == maps[name, "surrogate"].input_box


@pytest.mark.parametrize(("name", "kind"), CASES)
def test_shapes_and_step_matches_step_with_jacobian(maps: dict, systems: dict, name: str, kind: str) -> None:
    model, call = maps[name, kind], _caller(maps[name, kind])
    nx, nu = model.nx, model.nu
    for lead in [(1,), (3,), (2, 3)]:
        x, u = _points(systems[name], lead, seed=len(lead))
        x1 = call("step", x, u)
        y, A, B = call("step_with_jacobian", x, u)
        assert x1.shape == y.shape == (*lead, nx)
        assert A.shape == (*lead, nx, nx) and B.shape == (*lead, nx, nu)
        assert np.all(np.isfinite(x1)) and np.all(np.isfinite(A)) and np.all(np.isfinite(B))
        np.testing.assert_allclose(y, x1, rtol=1e-12, atol=1e-12)
        flat = call("step", x.reshape(-1, nx), u.reshape(-1, nu))  # rows are independent problems
        np.testing.assert_allclose(x1.reshape(-1, nx), flat, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize(("name", "kind"), CASES)
def test_jacobians_match_finite_differences(maps: dict, systems: dict, name: str, kind: str) -> None:
    model, call = maps[name, kind], _caller(maps[name, kind])
    nx, nu = model.nx, model.nu
    x, u = _points(systems[name], (2,), seed=7)
    _, A, B = call("step_with_jacobian", x, u)
    z = np.concatenate((x, u), -1)  # (2, n): perturb every input coordinate of every sample in one batch
    n = nx + nu
    scale = np.maximum(np.abs(z), 1.0)
    dz = FD_EPS * scale[:, None, :] * np.eye(n)  # (2, n, n)
    zp, zm = z[:, None, :] + dz, z[:, None, :] - dz
    fp, fm = call("step", zp[..., :nx], zp[..., nx:]), call("step", zm[..., :nx], zm[..., nx:])
    fd = ((fp - fm) / (2 * FD_EPS * scale[:, :, None])).swapaxes(-1, -2)  # (2, nx, n)
    jac = np.concatenate((A, B), -1)
    np.testing.assert_allclose(jac, fd, rtol=1e-5, atol=1e-6 * max(1.0, np.abs(jac).max()))


@pytest.mark.parametrize(("name", "kind"), CASES)
def test_numpy_fast_path_is_the_same_map(maps: dict, systems: dict, name: str, kind: str) -> None:
    model = maps[name, kind]
    fast = numpy_path(model)
    if kind == "rk4_torch":  # the torch baseline keeps its own Jacobians: no fast path
        assert fast is None
        return
    assert fast is not None and fast.array_api == "numpy"
    assert fast.tau == model.tau and tuple(fast.state_names) == tuple(model.state_names)
    x, u = _points(systems[name], (4,), seed=3)
    want = _caller(model)("step_with_jacobian", x, u)
    for got, ref in zip(fast.step_with_jacobian(x, u), want):
        np.testing.assert_allclose(got, ref, rtol=1e-11, atol=1e-11)


@pytest.mark.parametrize(("name", "kind"), CASES)
def test_horizon_ocp_takes_every_flow_map(maps: dict, systems: dict, name: str, kind: str) -> None:
    """The OCP predicts with any map through the interface alone: its rollout and Gauss-Newton Jacobian agree
    with the map's own steps, and a numpy-only map refuses autograd with a clear error."""
    model, system, H = maps[name, kind], systems[name], 3
    ocp = HorizonOCP(model, H, [1.0] * model.nx, [1e-6] * model.nu)
    x, u = _points(system, (2,), seed=5)
    U = np.repeat(u[:, None, :], H, axis=1)
    X = ocp.rollout(x, U)
    call, xi = _caller(model), x
    for i in range(H):
        xi = call("step", xi, U[:, i])
        np.testing.assert_allclose(X[:, i], xi, rtol=1e-10, atol=1e-10)
    x_ref, u_prev = np.zeros((2, H, model.nx)), np.zeros((2, model.nu))
    r, jac = ocp.residuals_and_jacobian(x, U, x_ref, u_prev)
    assert r.shape == (2, H * (model.nx + model.nu)) and jac.shape == (2, r.shape[1], H * model.nu)
    Ut = torch.from_numpy(U).requires_grad_(True)
    if model.array_api == "numpy":
        with pytest.raises(TypeError, match="numpy arrays only"):
            ocp.cost(torch.from_numpy(x), Ut, torch.from_numpy(x_ref), torch.from_numpy(u_prev))
    else:
        cost = ocp.cost(torch.from_numpy(x), Ut, torch.from_numpy(x_ref), torch.from_numpy(u_prev)).sum()
        (grad,) = torch.autograd.grad(cost, Ut)  # the torch path stays differentiable
        want = 2 * np.einsum("bm,bmn->bn", r, jac).reshape(grad.shape)
        np.testing.assert_allclose(grad.numpy(), want, rtol=1e-6, atol=1e-9)


def test_numpy_flow_without_names_gets_generic_ones() -> None:
    surrogate = load_surrogate()
    flow = NumpyFlow.from_pinn(surrogate.model, surrogate.tau)
    assert flow.state_names == ("x0", "x1", "x2", "x3") and flow.input_names == ("u0", "u1")
    assert flow.state_box == surrogate.state_box and flow.numpy_flow() is flow


def test_check_flow_map_names_what_is_missing() -> None:
    with pytest.raises(TypeError, match="lacks.*step_with_jacobian"):
        HorizonOCP(object(), 3, [1.0], [1.0])


@pytest.mark.slow  # compiles the Panda's RK4 (~40 s on a fresh machine)
def test_a_compiled_jacobian_with_structural_zeros_comes_out_right() -> None:
    # the Panda's flow does not depend on q1 except through q1 itself (gravity compensated, M free of q1): CasADi's
    # Jacobian is sparse there, and its nonzeros read as dense rows were garbage until outputs were densified
    system = load_system("panda")
    fast, slow = CompiledRK4(system, system.tau, 1e-3), RK4Model(system, system.tau, 1e-3)  # stable at 1 ms
    x, u = _points(system, (2,), 4)
    _, a, b = fast.step_with_jacobian(x, u)
    _, at, bt = slow.step_with_jacobian(torch.from_numpy(x), torch.from_numpy(u))
    np.testing.assert_allclose(a, at.numpy(), atol=1e-9)
    np.testing.assert_allclose(b, bt.numpy(), atol=1e-9)


def test_a_training_size_batch_runs_on_torchs_threads_with_the_serial_result(systems: dict) -> None:
    from pinnmpc.systems.compiled import ROWS_PER_THREAD, batch_threads

    rhs = systems["planar3"].compiled.rhs
    n = 4 * ROWS_PER_THREAD
    rng = np.random.default_rng(0)
    x, u = rng.uniform(-1, 1, (n, 6)), rng.uniform(-1, 1, (n, 3))
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        assert batch_threads(n) == 1
        (serial,) = rhs(x, u)
        torch.set_num_threads(2)
        assert batch_threads(n) == 2 and batch_threads(ROWS_PER_THREAD) == 1  # a controller's rows stay serial
        (threaded,) = rhs(x, u)
    finally:
        torch.set_num_threads(before)
    assert {key[1] for key in rhs._calls if key[0] == n} == {1, 2}  # both evaluations really ran
    np.testing.assert_array_equal(threaded, serial)  # rows are independent: bit-identical
    assert np.isfinite(serial).all() and np.abs(serial).max() > 0


def test_a_sparse_compiled_output_is_refused_not_misread() -> None:
    sym = ca.SX.sym("x", 2)
    with pytest.raises(ValueError, match="outputs \\[0\\] are sparse; expected dense outputs"):
        BatchedFunction(ca.Function("sparse", [sym], [ca.jacobian(ca.vertcat(sym[0], 0), sym)]))


def test_exact_values_take_the_true_models_values_and_the_surrogates_jacobians(maps: dict, systems: dict) -> None:
    for name in SYSTEMS:
        exact, net = maps[name, "rk4_compiled"], maps[name, "numpy"]
        model = ExactValues(maps[name, "surrogate"], exact)
        check_flow_map(model)
        assert model.array_api == "numpy" and model.approximate_jacobians and numpy_path(model) is model
        assert (model.state_box, model.input_box) == (net.state_box, net.input_box)  # valid where the network is
        x, u = _points(systems[name], (2, 3), seed=11)
        y, A, B = model.step_with_jacobian(x, u)
        np.testing.assert_array_equal(y, exact.step(x, u))
        np.testing.assert_array_equal(model.step(x, u), y)
        _, A_net, B_net = net.step_with_jacobian(x, u)
        np.testing.assert_array_equal(A, A_net)
        np.testing.assert_array_equal(B, B_net)
        assert not np.allclose(y, net.step(x, u), atol=1e-6)  # the values really are another model's


def test_exact_values_refuse_a_model_of_another_system(maps: dict) -> None:
    surrogate = maps["powercube", "surrogate"]
    with pytest.raises(ValueError, match="the exact model's states .* differ from the surrogate's"):
        ExactValues(surrogate, CompiledRK4(load_system("planar3"), surrogate.tau, 0.0025))
    with pytest.raises(ValueError, match="tau=0.1 differs from the surrogate's tau=0.2"):
        ExactValues(surrogate, CompiledRK4(load_system("powercube"), 0.1, 0.02))


def test_the_numpy_path_names_wrong_shapes() -> None:
    flow = load_surrogate().numpy_flow()
    for x0, u in ((np.zeros(3), np.zeros(2)), (np.zeros(4), np.zeros(3))):
        for call in (flow.step, flow.step_with_jacobian):
            with pytest.raises(ValueError, match=r"expected \(\.\.\., 4\) and \(\.\.\., 2\)"):
                call(x0, u)


@pytest.mark.parametrize(("name", "kind"), CASES)
def test_the_input_jacobian_alone_is_step_with_jacobians_b(maps: dict, systems: dict, name: str, kind: str) -> None:
    """A cold solve's node inputs need only B: the OCP's input-only path gives step_with_jacobian's values and B
    (the numpy network's own cheaper pass, every other map through the full one) on numpy arrays."""
    model = numpy_path(maps[name, kind])
    if model is None:  # the torch baseline: the lifted solver needs a numpy map
        return
    ocp = HorizonOCP(model, 4, [1.0] * model.nx, [1e-6] * model.nu)
    x, u = _points(systems[name], (2, 4), seed=11)
    y, b = ocp.step_with_input_jacobian(x, u)
    want_y, _, want_b = ocp.step_with_jacobian(x, u)
    assert b.shape == (2, 4, model.nx, model.nu)
    np.testing.assert_allclose(y, want_y, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(b, want_b, rtol=1e-13, atol=1e-13)


def test_the_input_jacobian_alone_with_a_prior_and_through_a_wrapper(systems: dict) -> None:
    """The shipped planar3 network (a frozen-arm prior, periodic angles) gives the same B by its input-only pass;
    a map wrapping it (the previous input's flow) is not handed its inner map's method but takes the full pass."""
    flow = load_surrogate(system="planar3").numpy_flow()
    ocp = HorizonOCP(flow, 3, [1.0] * flow.nx, [1e-6] * flow.nu)
    x, u = _points(systems["planar3"], (5,), seed=12)
    y, b = ocp.step_with_input_jacobian(x, u)
    want_y, _, want_b = flow.step_with_jacobian(x, u)
    np.testing.assert_allclose(y, want_y, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(b, want_b, rtol=1e-13, atol=1e-13)
    wrapped = PreviousInputFlow(load_surrogate().numpy_flow())  # the PowerCube's 2 inputs read as (u, u_prev)
    ocp = HorizonOCP(wrapped, 3, [1.0] * wrapped.nx, [1e-6] * wrapped.nu)
    s, v = np.zeros((5, wrapped.nx)), np.full((5, wrapped.nu), 0.1)
    y, b = ocp.step_with_input_jacobian(s, v)
    want_y, _, want_b = ocp.step_with_jacobian(s, v)
    assert b.shape == (5, wrapped.nx, wrapped.nu)
    np.testing.assert_array_equal(y, want_y)
    np.testing.assert_array_equal(b, want_b)


def _deferred_estimate(ocp: HorizonOCP, x: np.ndarray, u: np.ndarray, before: tuple[np.ndarray, np.ndarray]) -> None:
    """A deferred offset-free estimate (HorizonOCP.defer_estimate) against the same OCP without one: the pass over
    the nodes gives their Jacobians as alone and their step plus the d that the estimator's step F(x_prev, u_prev)
    gave, computed once; a later use of d reads it, a new deferral read as d settles by a step of its own."""
    want_y, want_a, want_b = ocp.step_with_jacobian(x, u)
    seen: list[np.ndarray] = []

    def update(step: np.ndarray) -> np.ndarray:
        seen.append(step)
        return 0.5 * (before[0] - step)

    ocp.defer_estimate(*before, update)
    y, a, b = ocp.step_with_jacobian(x, u)
    assert len(seen) == 1
    np.testing.assert_allclose(seen[0], ocp.flow.step(*before), rtol=1e-13, atol=1e-13)
    d = ocp.disturbance
    np.testing.assert_array_equal(d, 0.5 * (before[0] - seen[0]))
    np.testing.assert_allclose(y, want_y + d, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(a, want_a, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(b, want_b, rtol=1e-13, atol=1e-13)
    ocp.step_with_jacobian(x, u)
    assert len(seen) == 1
    ocp.defer_estimate(*before, update)
    np.testing.assert_allclose(ocp.disturbance, d, rtol=1e-13, atol=1e-13)
    assert len(seen) == 2


@pytest.mark.parametrize(("name", "kind"), CASES)
def test_the_estimators_step_rides_with_the_nodes(maps: dict, systems: dict, name: str, kind: str) -> None:
    """Every numpy map: the numpy network carries the estimator's step as a row of values beside the nodes, a
    second-order one and the compiled true model in a pass of their own; the OCP's answers are the same."""
    model = numpy_path(maps[name, kind])
    if model is None:  # the torch baseline: no numpy pass over nodes
        return
    ocp = HorizonOCP(model, 4, [1.0] * model.nx, [1e-6] * model.nu)
    x, u = _points(systems[name], (1, 4), seed=13)
    x_prev, u_prev = _points(systems[name], (), seed=14)
    _deferred_estimate(ocp, x, u, (x_prev, u_prev))
    if getattr(type(model), "step_with_jacobian_plus", None) is not None:  # the pass itself
        got = model.step_with_jacobian_plus(x, u, x_prev[None], u_prev[None])
        for g, w in zip(got, (*model.step_with_jacobian(x, u), model.step(x_prev[None], u_prev[None])), strict=True):
            assert g.shape == w.shape
            np.testing.assert_allclose(g, w, rtol=1e-13, atol=1e-13)


def test_the_estimators_step_rides_with_a_prior_and_through_a_wrapper(systems: dict) -> None:
    """The shipped planar3 network (a frozen-arm prior: its value at the estimator's row) and the previous input's
    map around the PowerCube's network (its one pass, the input carried below)."""
    flow = load_surrogate(system="planar3").numpy_flow()
    x, u = _points(systems["planar3"], (1, 3), seed=15)
    before = _points(systems["planar3"], (), seed=17)
    _deferred_estimate(HorizonOCP(flow, 3, [1.0] * flow.nx, [1e-6] * flow.nu), x, u, before)
    wrapped = PreviousInputFlow(load_surrogate().numpy_flow())
    ocp = HorizonOCP(wrapped, 3, [1.0] * wrapped.nx, [1e-6] * wrapped.nu)
    rng = np.random.default_rng(16)
    s, v = rng.uniform(-0.3, 0.3, (1, 3, wrapped.nx)), rng.uniform(-0.3, 0.3, (1, 3, wrapped.nu))
    _deferred_estimate(ocp, s, v, (rng.uniform(-0.3, 0.3, wrapped.nx), rng.uniform(-0.3, 0.3, wrapped.nu)))


def test_a_stand_in_priors_pass_takes_every_rows_value_in_one_call() -> None:
    """The shipped Panda network (midpoint prior, another prior's Jacobian standing in): its pass over the nodes with
    the estimator's row takes the prior's value of every row in one call and its Jacobian apart, and answers as
    step_with_jacobian at the nodes and step at the row (to rounding: step's MLP pass is the values' own)."""
    flow = load_surrogate(system="panda").numpy_flow()
    assert flow.start.jacobian is not None and flow.approximate_jacobians
    panda = load_system("panda")
    x, u = _points(panda, (5,), seed=18)
    before = _points(panda, (1,), seed=19)
    got = flow.step_with_jacobian_plus(x, u, *before)
    for g, w in zip(got, (*flow.step_with_jacobian(x, u), flow.step(*before)), strict=True):
        np.testing.assert_allclose(g, w, rtol=1e-13, atol=1e-13)
