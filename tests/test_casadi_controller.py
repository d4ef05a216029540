"""The classical NMPC on the true model (controller=casadi): its model, closed loops on the scipy plant, fallback,
RTI and code generation. Real solvers and plants throughout; compiled libraries are cached across runs."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig, OmegaConf

from pinnmpc.controller.classical.nmpc import CasadiNMPC, build_casadi_nmpc
from pinnmpc.controller.classical.ocp import CasadiOCP, Solution, stable_rk4_steps
from pinnmpc.plant import ScipyPlant
from pinnmpc.systems import load_system

torch.set_num_threads(1)  # a training job shares this 2-core machine

CONF = Path(__file__).resolve().parents[1] / "conf"


@pytest.fixture(scope="module")
def systems() -> dict[str, Any]:
    return {name: load_system(name) for name in ("powercube", "planar3")}


RK4_SHOOTING = ["controller.rti=false", "controller.transcription=rk4", "controller.qpsol=qrqp"]  # what these test


@pytest.fixture(scope="module")
def base_cfg() -> Callable[..., dict]:
    """conf/controller/casadi.yaml composed with a system (as the closed loop composes it), as a plain dict,
    with dotted-key overrides."""
    composed: dict[str, DictConfig] = {}

    def _cfg(system: str, **overrides: Any) -> dict:
        if system not in composed:
            with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
                cfg = compose("closed_loop", overrides=["controller=casadi", f"system={system}", *RK4_SHOOTING])
            composed[system] = OmegaConf.create(OmegaConf.to_container(cfg.controller, resolve=True))
        cfg = composed[system].copy()
        for key, value in overrides.items():
            OmegaConf.update(cfg, key, value)
        return OmegaConf.to_container(cfg)

    return _cfg


@pytest.mark.parametrize("name", ["powercube", "planar3"])
def test_casadi_rhs_equals_torch_rhs(systems: dict, name: str) -> None:
    s = systems[name]
    f = s.casadi_rhs()
    nx, nu = len(s.state_names), len(s.input_names)
    rng = np.random.default_rng(0)
    x = rng.uniform(s.state_box.low, s.state_box.high, (20, nx))
    u = rng.uniform(s.input_box.low, s.input_box.high, (20, nu))
    expected = s.rhs(torch.from_numpy(x), torch.from_numpy(u)).numpy()
    got = np.asarray(f.map(20)(x.T, u.T)).T
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12)


def test_config_builds_the_documented_default(base_cfg: Callable[..., dict], systems: dict) -> None:
    cfg = base_cfg("powercube")
    assert cfg["kind"] == "casadi" and cfg["horizon"] == 5 and cfg["Q"] == [1.0, 1.0, 0.0, 0.0]
    c = build_casadi_nmpc(OmegaConf.create(cfg), systems["powercube"])  # a DictConfig works too
    assert isinstance(c, CasadiNMPC)
    assert (c.horizon, c.nx, c.nu) == (5, 4, 2)
    np.testing.assert_array_equal(c.low, [-0.5, -0.5])
    np.testing.assert_array_equal(c.high, [0.5, 0.5])
    assert c.describe()["solver"] == f"casadi-{cfg['solver']}"
    assert c.describe()["disturbance_gain"] == cfg["disturbance"]["gain"]


def test_rk4_model_matches_a_fine_integration(systems: dict) -> None:
    """The prediction model F (RK4 with the automatic sub-steps) is the system's flow over tau."""
    from scipy.integrate import solve_ivp

    s = systems["powercube"]
    ocp = CasadiOCP(s, 5, [1, 1, 0, 0], [1e-6, 1e-6], None, s.input_box.low, s.input_box.high)
    x, u = np.array([0.3, -0.4, 0.5, -0.2]), np.array([0.1, -0.05])
    exact = solve_ivp(lambda _t, y: s.rhs(y, u), (0, s.tau), x, method="DOP853", rtol=1e-12, atol=1e-12).y[:, -1]
    np.testing.assert_allclose(np.asarray(ocp.F(x, u)).ravel(), exact, atol=1e-6)


def hold_and_sine(system: Any, steps: int, horizon: int) -> np.ndarray:
    """A smooth reference from rest: each joint moves by a short sine around its start, (steps + H + 1, nx)."""
    nq = system.nq
    t = np.arange(steps + horizon + 1) * system.tau
    amp, w = 0.15 * np.ones(nq), 2 * np.pi / (t[-1] + system.tau)
    q = 0.2 + amp * np.sin(w * t)[:, None] * (1 - np.exp(-t / 0.5))[:, None]
    v = np.gradient(q, t, axis=0)
    return np.hstack([q, v])


@pytest.mark.parametrize("name", ["powercube", "planar3"])
def test_closed_loop_tracks_on_the_scipy_plant(base_cfg: Callable[..., dict], systems: dict, name: str) -> None:
    s = systems[name]
    c = build_casadi_nmpc(base_cfg(name), s)
    plant = ScipyPlant(s, s.tau)
    steps = 15
    ref = hold_and_sine(s, steps, c.horizon)
    x = ref[0].copy()
    for k in range(steps):
        u = c.make_step(x, ref[k + 1 : k + 1 + c.horizon])
        assert u.shape == (c.nu,) and np.all(np.isfinite(u))
        assert np.all(u >= c.low) and np.all(u <= c.high)
        x = plant.step(x, u)
    err = np.abs(x[: s.nq] - ref[steps, : s.nq])
    assert err.max() < 2e-3, err
    assert len(c.stats) == steps and not any(st.fallback for st in c.stats)
    assert all(st.converged for st in c.stats) and all(st.time_s > 0 for st in c.stats)
    c.reset()
    assert c.stats == []


def test_failed_solves_fall_back_to_the_shifted_plan(base_cfg: Callable[..., dict], systems: dict) -> None:
    s = systems["powercube"]
    c = build_casadi_nmpc(base_cfg("powercube"), s)
    ref = np.tile([0.2, 0.3, 0.0, 0.0], (c.horizon, 1))
    x = np.array([0.0, 0.0, 0.0, 0.0])
    c.make_step(x, ref)
    planned = c.plan
    assert not c.stats[-1].fallback
    bad = ref.copy()
    bad[2, 0] = np.nan  # a NaN reference: the solver cannot succeed
    u = c.make_step(x, bad)
    assert np.all(np.isfinite(u)) and np.all(u >= c.low) and np.all(u <= c.high)
    assert c.stats[-1].fallback and not c.stats[-1].converged
    np.testing.assert_allclose(u, planned[0])  # the previous plan, shifted
    # an impossible iteration budget (its iterate is the previous plan itself): also a fallback, within bounds
    cfg = base_cfg("powercube", **{"solvers.sqpmethod.max_iter": 0, "solver": "sqpmethod"})
    c0 = build_casadi_nmpc(cfg, s)
    u = c0.make_step(x, ref)
    assert c0.stats[-1].fallback and np.all(np.isfinite(u)) and np.all(u >= c0.low) and np.all(u <= c0.high)


def test_an_unconverged_solve_is_kept_when_its_simulated_inputs_beat_the_previous_plan(
    base_cfg: Callable[..., dict], systems: dict
) -> None:
    """Far off the reference (0.5 rad in every joint) Gauss-Newton SQP converges linearly: a solve stopped by its
    iteration cap applies its inputs when, simulated through the model, they cost less than the previous plan's."""
    s = systems["planar3"]
    x, ref = np.array([0.5, -0.5, 0.5, 0.0, 0.0, 0.0]), np.zeros((5, 6))
    steps = []
    for keep in (True, False):
        c = build_casadi_nmpc(base_cfg("planar3", keep_unconverged=keep), s)
        steps.append((c.make_step(x, ref), c.stats[-1], c))
    (u, kept, c), (u_off, fell_back, _) = steps
    assert kept.iterations == fell_back.iterations == base_cfg("planar3")["solvers"]["sqpmethod"]["max_iter"]
    assert not kept.fallback and not kept.converged and np.isfinite(kept.cost)
    assert fell_back.fallback and np.all(u_off == 0.0)  # the cold plan: zero inputs
    p = c.solver.p.copy()
    plan, zeros = np.vstack([u, c.plan[:-1]]), np.zeros((5, 3))  # the kept inputs, and the zero plan
    assert kept.cost == pytest.approx(c.ocp.rollout_cost(plan, p), rel=1e-12)  # the cost it was kept for
    assert c.ocp.rollout_cost(plan, p) < 0.5 * c.ocp.rollout_cost(zeros, p)
    # an iterate with non-finite multipliers would poison the next warm start: never kept
    bad = Solution(w=c._w.copy(), lam_x=np.full_like(c._w, np.nan), lam_g=np.zeros(c.ocp.ng), cost=0.0,
                   success=False, iterations=20, status="Maximum_Iterations_Exceeded")  # fmt: skip
    assert c._kept_cost(bad, p) is None


def test_rti_takes_one_step_per_sample(base_cfg: Callable[..., dict], systems: dict) -> None:
    s = systems["powercube"]
    c = build_casadi_nmpc(base_cfg("powercube", solver="sqpmethod", rti=True), s)
    assert c.describe()["solver"] == "casadi-sqpmethod-rti" and c.describe()["real_time"] is True
    plant = ScipyPlant(s, s.tau)
    ref = hold_and_sine(s, 8, c.horizon)
    x = ref[0].copy()
    for k in range(8):
        x = plant.step(x, c.make_step(x, ref[k + 1 : k + 1 + c.horizon]))
    assert c.stats[0].converged  # the first sample solves fully: there is nothing to iterate from yet
    assert all(st.iterations <= 1 and not st.fallback for st in c.stats[1:])
    assert np.abs(x[:2] - ref[8, :2]).max() < 2e-3


def test_codegen_on_and_off_agree(base_cfg: Callable[..., dict], systems: dict) -> None:
    s = systems["powercube"]
    x, ref = np.array([0.1, -0.2, 0.0, 0.1]), np.tile([0.15, -0.25, 0.0, 0.0], (5, 1))
    first = []
    for codegen, level in ((True, "-O2"), (False, "-O2"), (True, "-O1")):
        c = build_casadi_nmpc(base_cfg("powercube", solver="sqpmethod", codegen=codegen, codegen_opt=level), s)
        first.append(c.make_step(x, ref))
        assert c.stats[-1].converged
    np.testing.assert_allclose(first[0], first[1], atol=1e-6)
    np.testing.assert_allclose(first[2], first[0], atol=1e-9)


def test_bad_settings_are_rejected(base_cfg: Callable[..., dict], systems: dict) -> None:
    s = systems["powercube"]
    with pytest.raises(ValueError, match="needs solver=sqpmethod"):
        build_casadi_nmpc(base_cfg("powercube", solver="ipopt", rti=True), s)
    with pytest.raises(ValueError, match="expected one of"):
        build_casadi_nmpc(base_cfg("powercube", solver="snopt"), s)
    with pytest.raises(ValueError, match="controller.codegen_opt='-O9'"):
        build_casadi_nmpc(base_cfg("powercube", codegen_opt="-O9"), s)
    with pytest.raises(ValueError, match="x_ref must cover the horizon"):
        build_casadi_nmpc(base_cfg("powercube"), s).make_step(np.zeros(4), np.zeros((3, 4)))
    with pytest.raises(ValueError, match="controller.u_low=.* exceeds controller.u_high"):
        build_casadi_nmpc(base_cfg("powercube", u_low=[0.1, 0.1], u_high=[0.0, 0.0]), s)
    with pytest.raises(ValueError, match=r"controller.qpsoll: not a setting here; expected one of \[.*'qpsol'"):
        build_casadi_nmpc(base_cfg("powercube", qpsoll="hpipm"), s)  # a misspelt key is refused, not ignored
    for key, value in (("horizon", 2.7), ("rk4_steps", 2.5), ("rk4_steps", "abc"), ("horizon", True)):
        with pytest.raises(ValueError, match=f"controller.{key}={value!r}: expected a whole number"):
            build_casadi_nmpc(base_cfg("powercube", **{key: value}), s)  # never silently truncated


@pytest.mark.parametrize("notch", [None, True])  # null (the network's setting handed on by the bench): off
def test_dictconfig_and_disturbance_estimator(base_cfg: Callable[..., dict], systems: dict, notch) -> None:
    """With a plant the model does not know (friction +20 %), the offset-free estimator engages and stays bounded,
    with or without the notch."""
    s = systems["powercube"]
    cfg: DictConfig = OmegaConf.create(base_cfg("powercube", **{"disturbance.gain": 0.7, "disturbance.notch": notch}))
    c = build_casadi_nmpc(cfg, s)
    assert c.describe()["disturbance_gain"] == 0.7 and c.describe()["disturbance_notch"] is bool(notch)
    plant = ScipyPlant(s.with_mismatch(friction_scale=1.2), s.tau)
    ref = hold_and_sine(s, 6, c.horizon)
    x = ref[0].copy()
    for k in range(6):
        x = plant.step(x, c.make_step(x, ref[k + 1 : k + 1 + c.horizon]))
    d = c.disturbance
    assert d is not None and np.all(np.abs(d) <= np.array(cfg.disturbance.max_abs))
    assert np.abs(d).max() > 0


def test_a_solve_at_rest_is_repeated_on_smoothed_friction(base_cfg: Callable[..., dict], systems: dict) -> None:
    """Held at rest, joint B's sign(v) friction leaves the exact model's NLP without a smooth solution: the SQP
    runs into its cap and the controller would fall back; coulomb_width repeats the solve on tanh(v / width)."""
    s = systems["powercube"]
    x, ref = np.array([0.0, 0.5, 0.0, 0.0]), np.tile([0.0, 0.5, 0.0, 0.0], (5, 1))
    exact = build_casadi_nmpc(base_cfg("powercube", coulomb_width=None, keep_unconverged=False), s)
    exact.make_step(x, ref)
    assert exact.stats[-1].fallback and exact.describe()["smoothed_solves"] == 0
    smoothed = build_casadi_nmpc(base_cfg("powercube"), s)
    assert base_cfg("powercube")["coulomb_width"] == 1e-3  # the PowerCube's default (conf/system/powercube.yaml)
    plant = ScipyPlant(s, s.tau)
    for _ in range(3):
        x = plant.step(x, smoothed.make_step(x, ref))
    assert not any(st.fallback for st in smoothed.stats) and smoothed.describe()["smoothed_solves"] >= 1
    assert np.abs(x[:2] - ref[0, :2]).max() < 1e-4
    planar = build_casadi_nmpc(base_cfg("planar3", coulomb_width=1e-3), systems["planar3"])
    assert planar.smooth_solver is None  # no sign(v) term: nothing to smooth
    moving = np.array([0.3, -0.2, 0.4, 0.1])  # |dbeta| = 100 widths: the smoothed model is the exact one
    np.testing.assert_allclose(s.casadi_rhs(1e-3)(moving, [0.1, 0.2]), s.casadi_rhs()(moving, [0.1, 0.2]), atol=1e-12)
    with pytest.raises(ValueError, match="coulomb_width must be > 0"):
        s.casadi_rhs(0.0)


def test_a_smoothed_models_rk4_steps_see_its_slope_at_rest(systems: dict) -> None:
    """tanh(v / width) is steepest at v = 0; samples only near zero missed it for small widths (a probe's 1e-6 ran
    55 sub-steps where ~29000 were needed, and every smoothed solve failed)."""
    s = systems["powercube"]
    narrow = s.casadi_rhs(1e-5)
    assert stable_rk4_steps(s, s.tau, rhs=narrow, at_rest=True) > 4 * stable_rk4_steps(s, s.tau, rhs=narrow)
    assert CasadiOCP(s, 5, [1, 1, 0, 0], [1e-6] * 2, None, [-0.5] * 2, [0.5] * 2, coulomb_width=1e-5).rk4_steps > 2000
    assert stable_rk4_steps(s, s.tau) == stable_rk4_steps(s, s.tau, at_rest=True)  # the exact model: no such slope
