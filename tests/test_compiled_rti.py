"""The network controller's real-time step after its network call as one compiled function
(pinnmpc.controller.compiled_rti): the numpy path's arithmetic to rounding, including the steps it hands back to
numpy (a bound cutting the step short, a joint-limit penalty acting), and on a real closed loop."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from omegaconf import OmegaConf

from pinnmpc import load_surrogate, load_system
from pinnmpc.controller.box_step import newton_step
from pinnmpc.controller.build import build_nmpc
from pinnmpc.controller.compiled_rti import compiled_step, spd_solve
from pinnmpc.controller.shooting import linearise
from pinnmpc.plant.build import make_plant, simulated_arm
from pinnmpc.simulation.setup import system_reference

TIGHT = 1e-9  # relative: the same arithmetic in another order
STIFF = 1e-8  # absolute, rad/s: the Panda's Gauss-Newton matrix with an acting penalty (weight 1e5 against inputs
#   weighted 1e-6) carries rounding in the predictions into the step some 1e8 times larger


def controller(make_cfg: Any, name: str, compiled: bool, *overrides: str) -> tuple[Any, Any]:
    """The arm's configured network NMPC (a real-time iteration), its step compiled or not, and its config."""
    cfg = make_cfg("closed_loop", [f"system={name}", *overrides])
    solver = {"solvers": {"lifted_gauss_newton": {"compiled_step": compiled}}}
    return build_nmpc(OmegaConf.merge(cfg.controller, solver), load_surrogate(system=name), load_system(name)), cfg


def numpy_step(ocp: Any, nodes: np.ndarray, U: np.ndarray, *rest: Any) -> tuple[np.ndarray, ...]:
    """The lifted solver's numpy real-time step (LiftedGaussNewtonSolver._rti_steps, compiled_step false)."""
    ref, up, lo, hi, damping = rest
    pred, sens, _, _ = linearise(ocp, nodes, U)
    f, jtj, grad = ocp.gauss_newton_model(pred, sens, U, ref, up)
    delta, _, predicted, _ = newton_step(jtj, grad, U, lo, hi, damping)
    step = np.clip(U + delta, lo, hi) - U
    return U + step, pred + (sens @ step[..., None])[..., 0].reshape(pred.shape), f - predicted


def problem(nmpc: Any, name: str, seed: int, spread: float = 0.3) -> tuple[np.ndarray, ...]:
    """One real-time step's problem: nodes near a state drawn in the box, inputs drawn over the whole input box."""
    h, nx = nmpc.ocp.horizon, nmpc.ocp.nx
    rng, box = np.random.default_rng(seed), load_system(name).state_box
    centre = (np.asarray(box.low) + np.asarray(box.high)) / 2
    x = centre + spread * rng.uniform(np.asarray(box.low) - centre, np.asarray(box.high) - centre)
    nodes = x + np.cumsum(rng.normal(0, 0.01, (1, h, nx)), axis=1)
    lo, hi = np.tile(nmpc.u_low, h)[None], np.tile(nmpc.u_high, h)[None]
    u_prev = rng.uniform(nmpc.u_low, nmpc.u_high)[None]
    return nodes, rng.uniform(lo, hi), nodes + rng.normal(0, 0.05, nodes.shape), u_prev, lo, hi


def check(nmpc: Any, name: str, seeds: range, spread: float = 0.3, atol: float = 1e-12) -> set[bool]:
    """The compiled step against the numpy step on problems of these seeds; whether bounds cut the Newton steps."""
    solver, ocp = nmpc.solver, nmpc.ocp
    compiled, cuts = solver._compiled(ocp), set()
    for seed in seeds:
        nodes, U, *rest = problem(nmpc, name, seed, spread)
        net = ocp.step_with_jacobian(nodes, U.reshape(1, ocp.horizon, ocp.nu))
        step = compiled(net, nodes, U, *rest)
        cuts.add(step.cut)
        limits = ocp.joint_limits  # the C's answer on the joint limits: JointLimits.reached's on the same states
        want = [False, False] if limits is None else [bool(limits.reached(s)[0]) for s in (step.pred, step.states)]
        assert list(step.reach) == want
        got = compiled_step(compiled, ocp, nodes.copy(), U, tuple(rest), solver.damping)
        for g, w in zip(got[:3], numpy_step(ocp, nodes.copy(), U, *rest, solver.damping), strict=True):
            np.testing.assert_allclose(g, w, rtol=TIGHT, atol=atol)
        limits = ocp.joint_limits  # its last answer: whether the states it reached meet a joint-limit penalty
        assert got[3] == (limits is not None and bool(limits.reached(got[1]).any()))
    return cuts


def test_the_compiled_step_is_the_numpy_step_and_hands_cut_steps_back(make_cfg: Any) -> None:
    """PowerCube: inputs drawn over the whole box, so the Newton step leaves it on some problems (the active-set
    path finishes them in numpy) and not on others; every result the numpy path's."""
    assert check(controller(make_cfg, "powercube", True)[0], "powercube", range(8)) == {True, False}


def test_an_acting_joint_limit_penalty_joins_the_model_as_in_numpy(make_cfg: Any) -> None:
    """The Panda with its soft joint limits, the nodes spread over the whole box and a little past it: the penalty
    acts at some nodes (the numpy Gauss-Newton model takes the compiled chain's predictions), the results the numpy
    path's."""
    nmpc, _ = controller(make_cfg, "panda", True)
    nodes = problem(nmpc, "panda", 0, spread=1.1)[0]
    assert nmpc.ocp.limit_residuals(nodes).any()
    check(nmpc, "panda", range(3), spread=1.1, atol=STIFF)


def test_the_compiled_step_checks_the_joint_limits_as_numpy_does(make_cfg: Any) -> None:
    """The Panda's soft limits with their lookahead, nodes drawn near the middle of the box and over all of it: the
    compiled step's own answer (whether its predictions and the states it reaches meet the penalty) is
    JointLimits.reached's on both sides of the limits (check compares them problem by problem)."""
    nmpc, _ = controller(make_cfg, "panda", True)
    assert nmpc.ocp.joint_limits.lookahead > 0
    seen = set()
    for spread in (0.3, 1.1):
        for seed in range(3):
            nodes, U, *rest = problem(nmpc, "panda", seed, spread)
            net = nmpc.ocp.step_with_jacobian(nodes, U.reshape(1, nmpc.ocp.horizon, nmpc.ocp.nu))
            seen.update(nmpc.solver._compiled(nmpc.ocp)(net, nodes, U, *rest).reach)
        check(nmpc, "panda", range(3), spread=spread, atol=STIFF)
    assert seen == {True, False}


def test_a_closed_loop_tracks_alike_compiled_or_not(make_cfg: Any) -> None:
    """planar3 on its plant, 40 samples: the compiled and the numpy controller apply the same inputs to rounding."""
    loops = []
    for compiled in (True, False):
        nmpc, cfg = controller(make_cfg, "planar3", compiled)
        system = load_system("planar3")
        plant = make_plant(simulated_arm(system, cfg.system), cfg.plant, system.tau, cfg.system.get("robots"))
        ref = system_reference(cfg, system, system.tau)
        x, inputs = np.array(ref.x[0]), []
        for k in range(40):
            inputs.append(nmpc.make_step(x, ref.x[k + 1 : k + 1 + nmpc.horizon]))
            x = plant.step(x, inputs[-1])
        loops.append(np.array(inputs))
    assert np.abs(loops[0]).max() > 0
    np.testing.assert_allclose(loops[0], loops[1], rtol=1e-7, atol=1e-9)


@pytest.mark.parametrize("compiled", [True, False])
@pytest.mark.parametrize("push", [0.0, 1.9])
def test_the_warm_step_is_solve_on_one_problem_bit_for_bit(make_cfg: Any, push: float, compiled: bool) -> None:
    """The Panda on its plant, 25 samples, the controller's warm_step against solve() (the solver without it), its
    real-time step compiled or in numpy: the same inputs to the last bit; with joint 4's reference pushed past its
    limit every warm plan meets the penalty, so warm_step hands its step on to the full solve."""
    loops = []
    for direct in (True, False):
        nmpc, cfg = controller(make_cfg, "panda", compiled)
        if not direct:
            nmpc.solver.warm_step = None  # the batch path of solve()
        system = load_system("panda")
        plant = make_plant(simulated_arm(system, cfg.system), cfg.plant, system.tau, cfg.system.get("robots"))
        ref = np.array(system_reference(cfg, system, system.tau).x)
        ref[:, 3] += push
        x, inputs = np.array(ref[0]), []
        for k in range(25):
            inputs.append(nmpc.make_step(x, ref[k + 1 : k + 1 + nmpc.horizon]))
            x = plant.step(x, inputs[-1])
        loops.append((np.array(inputs), [s.iterations for s in nmpc.stats]))
        if direct:  # the direct path ran: the next sample's warm step is there to take
            args = (x, nmpc._U, ref[26 : 26 + nmpc.horizon], nmpc._u_prev, nmpc._low, nmpc._high, nmpc.warm)
            assert nmpc.solver.warm_step(nmpc.ocp, *args) is not None
    assert np.array_equal(loops[0][0], loops[1][0]) and loops[0][1] == loops[1][1]
    assert (min(loops[0][1][1:]) > 1) == (push > 0)  # solved on past the real-time step exactly where pushed


def test_a_warm_step_takes_bounds_that_changed_since_the_last_sample(make_cfg: Any) -> None:
    """planar3, 10 samples on its plant, then the warm step with the input box narrowed to its top tenth: the step's
    inputs keep within the new box (the rows kept from the samples before are the old box's, compared by value)."""
    nmpc, cfg = controller(make_cfg, "planar3", True)
    system = load_system("planar3")
    plant = make_plant(simulated_arm(system, cfg.system), cfg.plant, system.tau, cfg.system.get("robots"))
    ref = np.array(system_reference(cfg, system, system.tau).x)
    x = np.array(ref[0])
    for k in range(10):
        x = plant.step(x, nmpc.make_step(x, ref[k + 1 : k + 1 + nmpc.horizon]))
    high = nmpc._high.copy()
    low = high - 0.1 * (high - nmpc._low)
    assert (low > nmpc._U).any()  # the plan lies below the new box: a step bounded by the old one would stay there
    out = nmpc.solver.warm_step(nmpc.ocp, x, nmpc._U, ref[11 : 11 + nmpc.horizon], nmpc._u_prev, low, high, nmpc.warm)
    assert out is not None
    assert (out[0] >= low - 1e-12).all() and (out[0] <= high + 1e-12).all()


@pytest.mark.parametrize(("name", "horizon", "compiles"), [("powercube", 5, True), ("panda", 20, False)])
def test_only_small_steps_are_compiled(make_cfg: Any, name: str, horizon: int, compiles: bool) -> None:
    """compiled_max_flops: numpy's BLAS does a large step (the Panda at H = 20) faster than C without it."""
    nmpc, _ = controller(make_cfg, name, True, f"controller.horizon={horizon}")
    assert (nmpc.solver._compiled(nmpc.ocp) is not None) is compiles
    assert not controller(make_cfg, name, False, f"controller.horizon={horizon}")[0].solver._compiles(nmpc.ocp)


def test_one_problems_box_step_solves_its_free_variables_alone_as_the_batch_does() -> None:
    """masked_solve at batch 1 solves the free variables' own system; in a batch the masked whole: the same step."""
    from pinnmpc.controller.box_step import masked_solve

    rng = np.random.default_rng(0)
    jac = rng.normal(size=(2, 60, 30))
    hess, grad = jac.swapaxes(-1, -2) @ jac, rng.normal(size=(2, 30))
    fixed = rng.uniform(size=(2, 30)) < 0.4
    batch = masked_solve(hess, grad, fixed)
    for k in range(2):
        alone = masked_solve(hess[k : k + 1], grad[k : k + 1], fixed[k : k + 1])
        np.testing.assert_allclose(alone, batch[k : k + 1], rtol=1e-10, atol=1e-14)
        assert np.all(alone[fixed[k : k + 1]] == 0.0)


def test_one_problems_active_set_path_downdates_its_inverse_to_the_batchs_path() -> None:
    """At batch 1 the active-set path downdates one inverse as bounds are met (many here); the batch factors anew
    per segment: the same path, every step inside the box, and the model lower than the clipped Newton step's."""
    from pinnmpc.controller.box_step import active_set_path

    rng = np.random.default_rng(3)
    jac = rng.normal(size=(2, 120, 60))
    hess, grad = jac.swapaxes(-1, -2) @ jac + 1e-3 * np.eye(60), 400.0 * rng.normal(size=(2, 60))
    u, lo, hi = rng.uniform(-1, 1, (2, 60)), -np.ones((2, 60)), np.ones((2, 60))
    fixed = np.zeros((2, 60), dtype=bool)
    batch = active_set_path(hess, grad, fixed, u, lo, hi)
    for k in range(2):
        alone = active_set_path(hess[k : k + 1], grad[k : k + 1], fixed[k : k + 1], u[k : k + 1], lo[k], hi[k])
        np.testing.assert_allclose(alone, batch[k : k + 1], rtol=1e-9, atol=1e-12)
        moved = u[k] + alone[0]
        assert np.all((moved >= lo[k] - 1e-12) & (moved <= hi[k] + 1e-12))
        assert np.sum(np.isclose(np.abs(moved), 1.0)) >= 10  # a long path: many bounds met on the way

        def model(d: np.ndarray, k: int = k) -> float:
            """The Gauss-Newton model of the step d."""
            return float(grad[k] @ d + d @ hess[k] @ d)

        clipped = np.clip(u[k] - 0.5 * np.linalg.solve(hess[k], grad[k]), lo[k], hi[k]) - u[k]
        assert model(alone[0]) < model(clipped)
    steps = newton_step(hess / 2, grad, u, lo, hi, 0.0)  # the same model: the step's own damping is 0
    assert steps.cut.all()
    for k in range(2):
        alone = newton_step(hess[k : k + 1] / 2, grad[k : k + 1], u[k : k + 1], lo[k], hi[k], 0.0)
        np.testing.assert_allclose(alone.delta, steps.delta[k : k + 1], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(alone.predicted, steps.predicted[k : k + 1], rtol=1e-9)
        assert alone.cut[0] == steps.cut[k]
    singular = np.zeros((1, 4, 4))  # no Cholesky factor: the batched path's solves
    singular[0, :2, :2] = np.eye(2)
    with pytest.raises(np.linalg.LinAlgError):
        active_set_path(singular, np.ones((1, 4)), np.zeros((1, 4), dtype=bool), np.zeros((1, 4)), -1.0, 1.0)


@pytest.mark.parametrize("seed", range(4))
def test_one_problems_newton_step_is_the_batchs(seed: int) -> None:
    """newton_step at batch 1 (one problem's 1-D path on one factor) against the same problem inside a batch of
    two (the batched masked solves and path): the same step, model decrease, projected gradient and cut, with
    variables starting on their bounds and steps the box cuts short."""
    rng = np.random.default_rng(seed)
    jac = rng.normal(size=(2, 50, 24))
    jtj, grad = jac.swapaxes(-1, -2) @ jac, rng.normal(size=(2, 24)) * 20.0
    lo, hi = np.full((2, 24), -1.0), np.full((2, 24), 1.0)
    u = rng.uniform(-1.0, 1.0, (2, 24))
    pinned = 4 if seed % 2 else 0  # on the bound the gradient points out of: fixed from the start (odd seeds)
    u[:, :pinned] = np.where(grad[:, :pinned] > 0, -1.0, 1.0)
    batch = newton_step(jtj, grad, u, lo, hi, 1e-6)
    assert batch.cut.all()
    for k in range(2):
        alone = newton_step(jtj[k : k + 1], grad[k : k + 1], u[k : k + 1], lo[k : k + 1], hi[k : k + 1], 1e-6)
        for got, want in zip(alone, batch, strict=True):
            assert got.shape == want[k : k + 1].shape
            np.testing.assert_allclose(got, want[k : k + 1], rtol=1e-9, atol=1e-12)
        assert np.all(alone.delta[0, :pinned] == 0.0)


def test_the_compiled_steps_cholesky_solve_is_numpys_and_breaks_down_to_nan() -> None:
    """spd_solve (the compiled step's solve) on damped Gauss-Newton matrices as the step forms them: numpy's solve to
    rounding; on a matrix with a zero pivot no number comes out, which compiled_step takes as its cue to finish the
    step in numpy."""
    rng = np.random.default_rng(0)
    solve = spd_solve(12)
    for _ in range(4):
        jac = rng.normal(size=(30, 12)) * np.logspace(-3, 2, 12)  # columns scaled over five decades
        hess = jac.T @ jac + 1e-9 * np.trace(jac.T @ jac) / 12 * np.eye(12)
        b = rng.normal(size=12)
        want = np.linalg.solve(hess, b)
        np.testing.assert_allclose(np.asarray(solve(hess, b)).ravel(), want, rtol=1e-7, atol=1e-12 * np.abs(want).max())
    broken = np.eye(12)
    broken[5, 5] = 0.0
    assert not np.isfinite(np.asarray(solve(broken, np.ones(12)))).all()
