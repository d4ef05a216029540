"""Joint limits are part of the problem: soft position limits in both OCPs, and references that leave the limits
refused. Real parts throughout: the shipped panda surrogate, the panda URDF, composed configs, CasADi solvers."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from pinnmpc.controller.build import build_nmpc
from pinnmpc.controller.classical.ocp import CasadiOCP
from pinnmpc.controller.ocp import HorizonOCP, JointLimits
from pinnmpc.references import ReferenceError, load_reference
from pinnmpc.simulation.setup import system_reference
from pinnmpc.surrogate import Surrogate, load_surrogate
from pinnmpc.systems import load_system

CONF = Path(__file__).resolve().parents[1] / "conf"
SHIPPED = Path(__file__).resolve().parents[1] / "pinnmpc" / "checkpoints"
H = 4  # a short horizon keeps the panda's Jacobians cheap
Q7 = [1.0] * 7 + [0.0] * 7
R7 = [1e-6] * 7
J4, J6 = 3, 5  # panda joint 4 (upper limit -0.0698 rad) and joint 6 (lower limit -0.0175 rad)


@pytest.fixture(scope="module")
def panda() -> Any:
    return load_system("panda")


@pytest.fixture(scope="module")
def surrogate() -> Surrogate:
    return load_surrogate(system="panda")


@pytest.fixture(scope="module")
def panda_cfg() -> Any:
    """The closed-loop config for the panda, composed as the CLI composes it."""
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("closed_loop", overrides=["system=panda"])


def limits(panda: Any, weight: float = 1e5, margin: float = 0.01) -> JointLimits:
    return JointLimits(panda.joint_limits.low, panda.joint_limits.high, weight, margin)


def near_limits() -> np.ndarray:
    """A panda state 0.1 rad below joint 4's upper limit and 0.1 rad above joint 6's lower one, at rest."""
    x = np.zeros(14)
    x[:7] = [0.0, 0.0, 0.0, -0.17, 0.0, 0.08, 0.0]
    return x


def pulling_reference(x: np.ndarray, steps: int) -> np.ndarray:
    """Reference states that pull joint 4 0.4 rad above its upper limit and joint 6 0.4 rad below its lower one."""
    ref = np.tile(x, (steps, 1))
    ref[:, J4], ref[:, J6] = 0.33, -0.42
    return ref


# -- where the limits come from ------------------------------------------------------------------------------------


def test_panda_limits_are_the_urdfs_and_the_state_boxs(panda: Any, panda_cfg: Any) -> None:
    assert panda.joint_limits == panda.urdf_limits
    assert panda.joint_limits.low == panda.state_box.low[:7] and panda.joint_limits.high == panda.state_box.high[:7]
    # both controllers read the same numbers, with the weight and margin of the system's control section
    for controller in ("nmpc", "casadi"):
        with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
            cfg = compose("closed_loop", overrides=["system=panda", f"controller={controller}"])
        node = OmegaConf.to_container(cfg.controller.joint_limits, resolve=True)
        low, high = list(panda.joint_limits.low), list(panda.joint_limits.high)
        assert node == {"low": low, "high": high, "weight": 1e5, "margin": 0.01, "lookahead": 0.05}
    # the PowerCube and planar3 joints turn all the way round: no limits, so their OCPs are unchanged
    for name in ("powercube", "planar3"):
        assert load_system(name).joint_limits is None
        with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
            assert compose("closed_loop", overrides=[f"system={name}"]).controller.joint_limits is None


@pytest.mark.parametrize(
    ("change", "fragment"),
    [
        ({"weight": 0.0}, "weight"),
        ({"margin": -0.1}, "margin"),
        ({"margin": 1.6}, "joint 3"),  # joint 4 spans 3.0 rad
        ({"low": [0.0] * 6}, "low has 6 entries"),
    ],
)
def test_bad_limits_are_refused(panda: Any, surrogate: Surrogate, change: dict, fragment: str) -> None:
    node = {"low": list(panda.joint_limits.low), "high": list(panda.joint_limits.high), "weight": 1e5, "margin": 0.01}
    with pytest.raises(ValueError, match=fragment):
        HorizonOCP(surrogate, H, Q7, R7, None, node | change)


# -- references outside the limits are refused ---------------------------------------------------------------------


def test_reference_outside_the_limits_is_refused(panda: Any, panda_cfg: Any, tmp_path: Path) -> None:
    t = np.arange(201) * 0.01
    x = np.tile(near_limits(), (len(t), 1))
    x[:, J4] = -0.17 + 0.2 * np.sin(np.pi * t / t[-1])  # peaks at t = 1 s at +0.03, 0.0998 past the limit -0.0698
    path = tmp_path / "too_far.npz"
    np.savez(path, t=t, x=x)
    limits_ = (panda.joint_limits.low, panda.joint_limits.high)
    with pytest.raises(ReferenceError) as err:
        load_reference(path, panda.tau, "default", panda.state_names, {}, None, limits_)
    message = str(err.value)
    assert "\n" not in message
    for part in (str(path), "q_joint4", "= 0.03 ", "t=1 s", "above its upper limit -0.0698", "0.0998"):
        assert part in message, (part, message)
    # the closed loop loads reference.path through the same check
    cfg = OmegaConf.merge(panda_cfg, {"reference": {"path": str(path)}})
    with pytest.raises(ReferenceError, match="q_joint4"):
        system_reference(cfg, panda, panda.tau)
    # and so the built-ins: a waypoint path below joint 6's lower limit
    start = near_limits()[:7]
    start[J6] = 0.5
    end = start.copy()
    end[J6] = -0.2
    spec = {"kind": "waypoints", "joints": [{"q": [a, b], "durations": [1.0]} for a, b in zip(start, end)]}
    with pytest.raises(ReferenceError) as err:
        load_reference(None, panda.tau, "low6", panda.state_names, {"low6": spec}, None, limits_)
    assert "builtin:low6" in str(err.value) and "q_joint6 = -0.2 at t=1 s" in str(err.value)
    assert "below its lower limit -0.0175" in str(err.value)


def test_shipped_references_stay_inside_the_limits(panda: Any, panda_cfg: Any) -> None:
    for name in ("default", "random", "random-3"):
        cfg = OmegaConf.merge(panda_cfg, {"reference": {"name": name}})
        ref = system_reference(cfg, panda, panda.tau)
        assert len(ref) > 100


# -- the PINN OCP ----------------------------------------------------------------------------------------------------


def test_limit_jacobian_matches_finite_differences(panda: Any, surrogate: Surrogate) -> None:
    # a network whose numpy Jacobians are exact: the shipped panda.pt's prior Jacobian stands in (docs/design.md)
    exact = load_surrogate(SHIPPED / "panda-frozen.pt")
    assert surrogate.approximate_jacobians and not exact.approximate_jacobians
    ocp = HorizonOCP(exact, H, Q7, R7, [1e-3] * 7, limits(panda))
    assert ocp.n_limits == 7 and ocp.n_residuals == H * (14 + 7 + 7 + 7)
    x0 = near_limits()
    U = np.zeros((H, 7))
    U[:, J4], U[:, J6], U[:, 0] = 1.6, -1.4, 0.3  # drive both joints through their limits
    ref, u_prev = pulling_reference(x0, H), np.zeros(7)
    r, J = ocp.residuals_and_jacobian(x0, U, ref, u_prev)
    block = slice(H * (14 + 7 + 7), None)
    X = ocp.rollout(x0, U)
    lo, hi = ocp.joint_limits.inner
    assert np.count_nonzero(r[block]) >= 4  # several penalties are active ...
    assert np.min(np.minimum(np.abs(X[:, :7] - lo), np.abs(X[:, :7] - hi))) > 1e-3  # ... none at its kink
    np.testing.assert_allclose(r[block], ocp.limit_residuals(X).ravel(), rtol=0, atol=1e-11)

    def residuals(u: np.ndarray) -> np.ndarray:
        u = u.reshape(H, 7)
        return ocp.residuals(ocp.rollout(x0, u), u, ref, u_prev)

    eps = 1e-4  # central differences: rounding dominates below ~1e-5 (3e-6 off at 1e-6), truncation ~4e-8 here
    fd = np.stack(
        [(residuals(U.ravel() + eps * e) - residuals(U.ravel() - eps * e)) / (2 * eps) for e in np.eye(H * 7)], -1
    )
    assert np.abs(J[block]).max() > 1.0  # sqrt(1e5) times position sensitivities of up to ~tau
    np.testing.assert_allclose(J[block], fd[block], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(J, fd, rtol=1e-6, atol=1e-6)
    # the torch path (autograd solvers) and the lifted solver's normal equations agree with it
    rt, Jt = ocp.residuals_and_jacobian(*(torch.from_numpy(a) for a in (x0, U, ref, u_prev)))
    np.testing.assert_allclose(rt.numpy(), r, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(Jt.numpy(), J, rtol=0, atol=1e-10)
    _, _, sens = ocp.jacobian_rollout(x0[None], U.reshape(1, -1), ref[None], u_prev[None])
    cost, jtj, grad = ocp.gauss_newton_model(X[None], sens.reshape(1, H * 14, -1), U.reshape(1, -1), ref, u_prev)
    np.testing.assert_allclose(cost[0], r @ r, rtol=1e-12)
    np.testing.assert_allclose(jtj[0], J.T @ J, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(grad[0], 2 * J.T @ r, rtol=1e-12, atol=1e-9)


def test_inactive_limits_change_nothing(panda: Any, surrogate: Surrogate) -> None:
    """Away from the limits the OCP with limits has the same cost, gradient and solution as the one without."""
    x0 = np.zeros(14)
    x0[:7] = [0.0, 0.0, 0.0, -1.5, 0.0, 1.5, 0.0]
    ref = np.tile(x0, (H, 1))
    ref[:, :7] += 0.05
    U = np.full((H, 7), 0.2)
    free = HorizonOCP(surrogate, H, Q7, R7)
    limited = HorizonOCP(surrogate, H, Q7, R7, None, limits(panda))
    r, J = free.residuals_and_jacobian(x0, U, ref, np.zeros(7))
    rl, Jl = limited.residuals_and_jacobian(x0, U, ref, np.zeros(7))
    np.testing.assert_array_equal(rl[: r.size], r)
    np.testing.assert_array_equal(rl[r.size :], 0.0)
    np.testing.assert_array_equal(Jl[: r.size], J)
    np.testing.assert_array_equal(Jl[r.size :], 0.0)


@pytest.mark.parametrize(
    "solver", ["lifted_gauss_newton", "gauss_newton", pytest.param("lbfgs", marks=pytest.mark.slow)]
)
def test_plans_stay_within_the_limits(panda: Any, surrogate: Surrogate, solver: str) -> None:
    """A reference 0.4 rad beyond two limits: the plan stops short of them (and would not without the limits)."""
    x0 = near_limits()
    ref = pulling_reference(x0, H)
    low, high = np.array(panda.joint_limits.low), np.array(panda.joint_limits.high)
    reached = {}
    # the free plan by the Gauss-Newton solver (the reference pulls past the limits), the limited one by each solver
    for label, jl, by in (("free", None, "lifted_gauss_newton"), ("limited", limits(panda), solver)):
        cfg = {"horizon": H, "Q": Q7, "R": R7, "solver": by, "disturbance": {"gain": 0.0}, "joint_limits": jl}
        if by == "lbfgs":
            cfg["solvers"] = {"lbfgs": {"max_iter": 30, "rounds": 5}}
        nmpc = build_nmpc(cfg, surrogate)
        args = [torch.from_numpy(a[None]) for a in (x0, ref, np.zeros((H, 7)), np.zeros(7))]
        U, _, _ = nmpc.solve(*args)
        reached[label] = nmpc.ocp.rollout(x0, U[0].numpy())[:, :7]
    assert reached["free"][:, J4].max() > high[J4] + 0.05  # without limits the plan runs past joint 4's
    assert np.all(reached["limited"] <= high + 1e-3) and np.all(reached["limited"] >= low - 1e-3)
    assert reached["limited"][-1, J4] > high[J4] - 0.03  # it still goes as far as the margin lets it


def test_closed_loop_on_the_model_stays_inside_the_limits(panda: Any, surrogate: Surrogate, panda_cfg: Any) -> None:
    """The shipped controller config, its own model as the plant: every command it gives keeps the predicted arm
    inside the limits while the reference pulls 0.4 rad beyond them. (On the RK45 plant the arm stays within the
    model's one-step error of the limits: the margin covers an accurate network's, not the first panda network's.)"""
    cfg = OmegaConf.merge(panda_cfg.controller, {"horizon": H})
    nmpc = build_nmpc(cfg, surrogate)
    model = surrogate.numpy_flow()
    x = near_limits()
    ref = pulling_reference(x, 15 + H)
    qs = []
    for k in range(15):
        x = model.step(x[None], nmpc.make_step(x, ref[k + 1 : k + 1 + H])[None])[0]
        qs.append(x[:7])
    qs = np.array(qs)
    low, high = np.array(panda.joint_limits.low), np.array(panda.joint_limits.high)
    assert not any(s.fallback for s in nmpc.stats)
    assert np.all(qs <= high) and np.all(qs >= low)
    # it goes as far as the margin lets it (with the anchored network it then chatters at the limit between the
    # input bounds rather than settling: docs/results.md)
    assert qs[:, J4].max() > high[J4] - 0.012 and qs[:, J6].min() < low[J6] + 0.012


# -- the classical OCP sees the same problem ---------------------------------------------------------------------------


def test_casadi_ocp_has_the_same_limit_penalty(panda: Any, surrogate: Surrogate) -> None:
    """The classical NLP's cost at given states and inputs equals the PINN OCP's, limit penalties active."""
    jl = limits(panda)
    nlp = CasadiOCP(panda, H, Q7, R7, None, panda.input_box.low, panda.input_box.high, rk4_steps=1, joint_limits=jl)
    pinn = HorizonOCP(surrogate, H, Q7, R7, None, jl)
    rng = np.random.default_rng(0)
    x0 = near_limits()
    X = x0 + rng.normal(0.0, 0.1, (H, 14))
    X[:, J4], X[:, J6] = [-0.2, -0.075, -0.05, 0.0], [0.1, 0.0, -0.01, -0.05]  # some past (limit - margin), some not
    U = rng.uniform(-1.0, 1.0, (H, 7))
    ref = pulling_reference(x0, H)
    assert np.count_nonzero(pinn.limit_residuals(X)) == 5
    w, p = np.zeros(nlp.nw), np.zeros(nlp.np)
    w[nlp.ix[0]], w[nlp.ix[1:]], w[nlp.iu] = x0, X, U
    p[nlp.p_ref] = ref.ravel()
    f = float(ca.Function("f", [nlp.nlp["x"], nlp.nlp["p"]], [nlp.nlp["f"]])(w, p))
    expected = float((pinn.residuals(X, U, ref, np.zeros(7)) ** 2).sum())
    assert f == pytest.approx(expected, rel=1e-12)


def test_casadi_plans_stay_within_the_limits() -> None:
    """The classical NMPC (sqpmethod, Gauss-Newton Hessian) with a limit the PowerCube's reference pulls past."""
    s = load_system("powercube")
    jl = JointLimits((-0.5, -0.5), (0.3, 0.5), 1e5, 0.01)
    ocp = CasadiOCP(s, 5, [1, 1, 0, 0], [1e-6, 1e-6], None, s.input_box.low, s.input_box.high, joint_limits=jl)
    quiet = {"print_iter": False, "print_header": False}
    solver = ocp.solver("sqpmethod", {"qpsol": "qrqp", "qpsol_options": quiet}, codegen=False)
    x0 = np.array([0.1, 0.0, 0.0, 0.0])
    solver.w0[ocp.ix] = x0
    solver.p[ocp.p_x0] = x0
    solver.p[ocp.p_ref] = np.tile([0.9, 0.2, 0.0, 0.0], 5)
    sol = solver()
    assert sol.success, sol.status
    alpha = sol.w[ocp.ix[1:, 0]]
    assert 0.28 < alpha.max() <= 0.3 - 0.01 + 1e-4, alpha  # at the margin, with the reference at 0.9


def test_panda_input_rate_weight_is_the_systems_and_shared_by_both_controllers(make_cfg) -> None:
    loop, bench = make_cfg("closed_loop", ["system=panda"]), make_cfg("bench", ["system=panda"])
    assert list(loop.controller.R_rate) == list(loop.system.control.R_rate) and len(loop.controller.R_rate) == 7
    assert list(bench.classical.controller.R_rate) == list(bench.controller.R_rate) == list(loop.controller.R_rate)
    assert make_cfg("closed_loop", []).controller.R_rate is None  # the PowerCube keeps the paper's cost
    override = make_cfg("closed_loop", ["system=panda", "controller.R_rate=null"])
    assert override.controller.R_rate is None


def test_real_time_exact_values_stay_inside_the_limits(panda: Any, tmp_path: Path) -> None:
    """controller=exact on the Panda is a real-time iteration; steps from the last plan's linearisation did not follow
    the limit penalty switching on, and plans held at the limits crossed them on the plant. Such samples are now
    solved fully: on a reference that drives every joint onto its upper limit in 4 s and holds it there, the arm
    stays inside (before: 18 of 155 steps past a limit, by up to 7.6 mrad)."""
    from pinnmpc.simulation.run import run_closed_loop

    t = np.arange(0.0, 8.0 + 1e-9, panda.tau)
    s = np.clip(t / 4.0, 0.0, 1.0)
    blend, dblend = s**3 * (10 - 15 * s + 6 * s**2), 30 * s**2 * (1 - s) ** 2 / 4.0
    start, high = np.array([0.0, 0.0, 0.0, -1.5, 0.0, 1.5, 0.0]), np.array(panda.joint_limits.high)
    path = tmp_path / "onto_limits.npz"
    np.savez(path, t=t, x=np.hstack([start + np.outer(blend, high - start), np.outer(dblend, high - start)]))
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        overrides = ["system=panda", "controller=exact", f"reference.path={path}", "progress=false", "plots=false"]
        cfg = compose("closed_loop", overrides=overrides)
    m = run_closed_loop(cfg, tmp_path / "run")
    q = np.load(tmp_path / "run" / "trajectory.npz")["x"][:, :7]
    assert m["status"] == "ok" and m["real_time"] and m["prediction"] == "exact_values"
    assert np.all(q <= high), (q - high).max(0)
    assert m["joint_limit_samples"] == 0 and m["joint_limit_excess_max"] == 0.0  # what metrics.json says of it
