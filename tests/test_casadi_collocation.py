"""Radau IIA collocation in the classical NMPC (controller.transcription=radau): the method, its one-period map, the
Jacobian it assembles, HPIPM on the stage structure, short closed loops and bad settings. Real CasADi, solvers and
plants throughout; compiled libraries are cached across runs."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import casadi as ca
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig, OmegaConf
from scipy.integrate import solve_ivp

from pinnmpc.controller.classical.collocation import RadauOCP, inverse_dynamics, radau_tableau
from pinnmpc.controller.classical.nmpc import build_casadi_nmpc
from pinnmpc.controller.classical.ocp import CasadiOCP
from pinnmpc.controller.classical.rti import rti_function, rti_solver
from pinnmpc.plant.scipy_plant import ScipyPlant
from pinnmpc.systems import load_system

torch.set_num_threads(1)  # other jobs share this machine

CONF = Path(__file__).resolve().parents[1] / "conf"


@pytest.fixture(scope="module")
def systems() -> dict[str, Any]:
    return {name: load_system(name) for name in ("powercube", "planar3")}


@pytest.fixture(scope="module")
def base_cfg() -> Callable[..., dict]:
    """conf/controller/casadi.yaml composed with a system, as a plain dict, with top-level overrides."""
    composed: dict[str, DictConfig] = {}

    def _cfg(system: str, **overrides: Any) -> dict:
        if system not in composed:
            with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
                cfg = compose("closed_loop", overrides=["controller=casadi", f"system={system}"])
            composed[system] = OmegaConf.create(OmegaConf.to_container(cfg.controller, resolve=True))
        return {**OmegaConf.to_container(composed[system]), **overrides}

    return _cfg


def ocp_of(system: Any, transcription: str, R_rate: list | None = None, **kw: Any) -> CasadiOCP:
    """A horizon-3 OCP tracking the joint angles."""
    nq = system.nq
    cls = RadauOCP if transcription == "radau" else CasadiOCP
    box = system.input_box
    return cls(system, 3, [1.0] * nq + [0.0] * nq, [1e-6] * nq, R_rate, box.low, box.high, **kw)


@pytest.mark.parametrize("stages", [1, 2, 3, 4])
def test_the_tableau_is_radau_iia(stages: int) -> None:
    A, b, c = radau_tableau(stages)
    assert c[-1] == pytest.approx(1.0) and np.all(np.diff(c) > 0)
    np.testing.assert_allclose(A.sum(axis=1), c, atol=1e-13)  # each stage integrates a constant exactly
    np.testing.assert_array_equal(b, A[-1])  # stiffly accurate: the end is the last stage
    for k in range(1, 2 * stages):  # order 2 s - 1: the weights integrate t^(k-1) exactly
        assert b @ c ** (k - 1) == pytest.approx(1.0 / k, abs=1e-13)


@pytest.mark.parametrize("name", ["powercube", "planar3", "rhs only"])
def test_the_inverse_dynamics_vanish_on_the_rhs(systems: dict, name: str) -> None:
    """M(q) a + h(q, v) - tau(q, v, u) = 0 at a = the rhs' accelerations: the same physics without M^-1 (a system
    that offers only casadi_rhs gets the residual a - f(x, u)'s accelerations)."""
    s = systems["planar3" if name == "rhs only" else name]
    only_rhs = SimpleNamespace(name=s.name, nq=s.nq, input_names=s.input_names, casadi_rhs=s.casadi_rhs)
    system = only_rhs if name == "rhs only" else s
    r, nq = inverse_dynamics(system), s.nq
    rng = np.random.default_rng(3)
    for _ in range(5):
        x, u = rng.uniform(s.state_box.low, s.state_box.high), rng.uniform(s.input_box.low, s.input_box.high)
        a = np.asarray(s.casadi_rhs()(x, u)).ravel()[nq:]
        scale = 1.0 + np.abs(a).max()
        assert np.abs(np.asarray(r(x[:nq], x[nq:], a, u))).max() < 1e-10 * scale


def moving_states(system: Any, ocp: RadauOCP, n: int = 4) -> list[tuple[np.ndarray, np.ndarray]]:
    """States moving at 0.3-0.6 rad/s per joint with the input that holds their accelerations at zero: smooth
    periods, no velocity reversal (where sign(v) friction makes any collocation low order)."""
    nq, rng, out = system.nq, np.random.default_rng(0), []
    for _ in range(n):
        q, v, zero = rng.uniform(-1, 1, nq), rng.uniform(0.3, 0.6, nq) * rng.choice([-1, 1], nq), np.zeros(nq)
        r0 = np.asarray(ocp.point(q, v, zero, zero)).ravel()
        ju = np.column_stack([np.asarray(ocp.point(q, v, zero, e)).ravel() - r0 for e in np.eye(nq)])  # linear in u
        out.append((np.r_[q, v], np.linalg.solve(ju, -r0)))
    return out


@pytest.mark.parametrize("name", ["powercube", "planar3"])
def test_one_period_map_matches_a_tight_integration(systems: dict, name: str) -> None:
    """Radau IIA, 3 stages, one interval per period, against solve_ivp (Radau, rtol = atol = 1e-11) of the system's
    rhs: positions within 2e-5 rad, velocities within 1e-3 rad/s; two intervals at least 16x closer (order 5)."""
    s = systems[name]
    one, two = ocp_of(s, "radau"), ocp_of(s, "radau", intervals=2)
    worst = {1: np.zeros(2 * s.nq), 2: np.zeros(2 * s.nq)}
    for x, u in moving_states(s, one):
        rhs = lambda _t, y, u=u: s.rhs(y, u)  # noqa: E731
        exact = solve_ivp(rhs, (0, s.tau), x, method="Radau", rtol=1e-11, atol=1e-11).y[:, -1]
        for k, ocp in ((1, one), (2, two)):
            worst[k] = np.maximum(worst[k], np.abs(np.asarray(ocp.F(x, u)).ravel() - exact))
    assert worst[1][: s.nq].max() < 2e-5 and worst[1][s.nq :].max() < 1e-3, worst[1]
    assert worst[2].max() < worst[1].max() / 16, (worst[1], worst[2])


@pytest.mark.parametrize(("name", "transcription"), [("planar3", "radau"), ("powercube", "radau"), ("planar3", "rk4")])
def test_the_assembled_jacobian_is_the_constraints_derivative(systems: dict, name: str, transcription: str) -> None:
    """What the compiled solvers use (the model's own derivative blocks, the previous input as a stage variable)
    equals CasADi's AD of g and of the Lagrangian, and the HPIPM stage dimensions cover the layout."""
    s = systems[name]
    kw = {"rk4_steps": 2} if transcription == "rk4" else {"intervals": 2}
    ocp = ocp_of(s, transcription, R_rate=[1e-4] * s.nq, **kw)
    w, p = ocp.nlp["x"], ocp.nlp["p"]
    _, g, jac = ocp._with_sensitivities(w, p)
    f = ca.Function("both", [w, p], [g, ocp.nlp["g"], jac, ca.jacobian(ocp.nlp["g"], w)])
    rng = np.random.default_rng(1)
    wv, pv = rng.uniform(-1, 1, ocp.nw), rng.uniform(-1, 1, ocp.np)
    g1, g2, j1, j2 = (np.asarray(ca.densify(v)) for v in f(wv, pv))
    np.testing.assert_allclose(g1, g2, atol=1e-12)
    np.testing.assert_allclose(j1, j2, rtol=1e-9, atol=1e-9)
    st = ocp.qp_structure()
    assert sum(st["nx"]) + sum(st["nu"]) == ocp.nw and sum(st["nx"][1:]) + sum(st["ng"]) == ocp.ng
    quiet = {"print_time": False, "print_header": False, "print_iteration": False, "print_status": False}
    grad = ca.nlpsol("ocp", "sqpmethod", ocp.nlp, {**quiet, "qpsol": "qrqp", "qpsol_options": {"print_header": False}})
    grad = grad.get_function("nlp_grad")  # the Lagrangian's gradient: CasADi's AD, and the compiled replacement
    args = [rng.uniform(-1, 1, grad.size1_in(i)) for i in range(grad.n_in())]
    for ad, mine in zip(grad(*args), ocp._like(grad, gauss_newton=False)(*args)):
        np.testing.assert_allclose(np.asarray(mine), np.asarray(ad), rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize(("transcription", "qpsol"), [("radau", "qrqp"), ("radau", "hpipm"), ("rk4", "hpipm")])
def test_the_condensed_step_is_the_full_qps_step(systems: dict, transcription: str, qpsol: str) -> None:
    """The real-time iteration's step, with the accelerations eliminated, equals the Gauss-Newton step of the full
    QP (solved by qrqp) from a point off the solution: previous input as a stage variable, a pressed input bound."""
    s = systems["planar3"]
    ocp = ocp_of(s, transcription, R_rate=[1e-4] * s.nq)
    rng = np.random.default_rng(2)
    w, p = 0.1 * rng.standard_normal(ocp.nw), np.zeros(ocp.np)
    p[ocp.p_ref] = np.tile([0.5, -0.3, 0.2, 0.0, 0.0, 0.0], ocp.horizon)
    _, g, jac = ocp._with_sensitivities(ocp.nlp["x"], ocp.nlp["p"])
    full = ca.Function("full", [ocp.nlp["x"], ocp.nlp["p"]], [ca.gradient(ocp.nlp["f"], ocp.nlp["x"]), g, jac])
    grad, gv, jv = full(w, p)
    hess = ca.triu2symm(ocp.gauss_newton(w, p, 1.0, np.zeros(ocp.ng)))
    qp = ca.conic("full_qp", "qrqp", {"h": hess.sparsity(), "a": jv.sparsity()}, {"print_iter": False})
    step = np.asarray(qp(h=hess, g=grad, a=jv, lba=-gv, uba=-gv, lbx=ocp.lbw - w, ubx=ocp.ubw - w)["x"]).ravel()
    u = (w + step)[ocp.iu]
    assert np.isclose(u, ocp.low).any() or np.isclose(u, ocp.high).any(), u  # a bound is active
    options = {"hpipm": {"inf": 1e6, "hpipm": {"mode": "robust"}}, "qrqp": {"print_iter": False}}[qpsol]
    solver = rti_solver(ocp, qpsol, options, rti_function(ocp), flow=lambda x, u: x)
    solver.w0[:], solver.p[:] = w, p
    sol = solver()
    assert sol.status == "RTI_step" and sol.iterations == 1
    # an interior point stops near, not on, an active bound, and inputs weighted 1e-8 leave the QP flat along them:
    # HPIPM's step agrees to its tolerances (a misread stage structure would be off by the inputs' whole range)
    tol = 1e-3 if qpsol == "hpipm" else 1e-9
    np.testing.assert_allclose(sol.w, w + step, rtol=tol, atol=tol)


def hold_and_sine(system: Any, steps: int, horizon: int) -> np.ndarray:
    """A smooth reference from rest: each joint moves by a short sine around its start, (steps + H + 1, nx)."""
    t = np.arange(steps + horizon + 1) * system.tau
    w = 2 * np.pi / (t[-1] + system.tau)
    q = 0.2 + 0.15 * np.ones(system.nq) * (np.sin(w * t) * (1 - np.exp(-t / 0.5)))[:, None]
    return np.hstack([q, np.gradient(q, t, axis=0)])


@pytest.mark.parametrize("rti", [False, True])
def test_radau_with_hpipm_tracks_on_the_scipy_plant(base_cfg: Callable[..., dict], systems: dict, rti: bool) -> None:
    s, steps = systems["planar3"], 12
    cfg = base_cfg("planar3", transcription="radau", collocation_intervals=2, qpsol="hpipm", rti=rti)
    c = build_casadi_nmpc(cfg, s)
    assert c.describe()["solver"] == "casadi-sqpmethod-hpipm-radau" + ("-rti" if rti else "")
    assert c.describe()["collocation_intervals"] == 2
    plant, ref = ScipyPlant(s, s.tau), hold_and_sine(s, steps, c.horizon)
    x = ref[0].copy()
    for k in range(steps):
        u = c.make_step(x, ref[k + 1 : k + 1 + c.horizon])
        assert np.all(u >= c.low) and np.all(u <= c.high)
        x = plant.step(x, u)
    assert np.abs(x[: s.nq] - ref[steps, : s.nq]).max() < 2e-3
    assert not any(st.fallback for st in c.stats)
    assert rti or all(st.converged for st in c.stats)
    assert not rti or all(st.iterations == 1 for st in c.stats[1:])  # the first solve is a full one
    x_prev, u_prev, guess = c._last  # the offset-free estimator's prediction: F, polished from the plan's unknowns
    exact = np.asarray(c.ocp.F(x_prev, u_prev)).ravel()
    np.testing.assert_allclose(c.solver.flow(x_prev, u_prev, guess), exact, rtol=1e-10, atol=1e-10)


def test_hpipm_and_qrqp_take_the_same_step(base_cfg: Callable[..., dict], systems: dict) -> None:
    """Both QP solvers of one converged solve, from rest off the reference: the same first input (HPIPM, an interior
    point, stops a little inside an input bound the plan presses against)."""
    s = systems["powercube"]
    x, ref = np.array([0.1, -0.2, 0.0, 0.0]), np.tile([0.3, 0.1, 0.0, 0.0], (5, 1))
    inputs = [
        build_casadi_nmpc(base_cfg("powercube", transcription="radau", qpsol=q, rti=False), s).make_step(x, ref)
        for q in ("qrqp", "hpipm")
    ]
    np.testing.assert_allclose(inputs[0], inputs[1], atol=1e-6)


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("transcription", "rk5"),
        ("collocation_stages", 0),
        ("collocation_intervals", 2.5),
        ("collocation_intervals", True),
        ("qpsol", "gurobi"),
    ],
)
def test_bad_settings_name_the_key(base_cfg: Callable[..., dict], systems: dict, key: str, value: Any) -> None:
    cfg = base_cfg("planar3", **{"transcription": "radau", "codegen": False, key: value})
    with pytest.raises(ValueError, match=rf"^controller\.{key}={value!r}: expected") as err:
        build_casadi_nmpc(cfg, systems["planar3"])
    assert "\n" not in str(err.value)
