"""The model's payload and armature, and identification: exact against MuJoCo, none leaves every number as it was,
and a fit to a robot whose truth is known recovers it."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("mujoco")

from pinnmpc import load_system  # noqa: E402 (after the skip)
from pinnmpc.plant.mujoco_robot import MujocoPlant  # noqa: E402
from pinnmpc.robot_data.collect import collect  # noqa: E402
from pinnmpc.robot_data.identify import identify  # noqa: E402
from pinnmpc.robot_data.identify_job import system_yaml, write_system  # noqa: E402
from pinnmpc.robot_data.logs import RobotLog, read_log, write_log  # noqa: E402
from pinnmpc.systems.urdf import Payload, RigidArm, locked_urdf  # noqa: E402

LAB = {  # planar3's lab robot without its dry friction: what the model can represent exactly
    "payload": {"mass": 0.5, "pos": [0.25, 0.0, 0.0]},
    "armature": [0.03, 0.015, 0.0025],
}


def states(arm: RigidArm, count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Random states and inputs in the arm's boxes."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(arm.state_box.low, arm.state_box.high, (count, 2 * arm.nq))
    return x, rng.uniform(arm.input_box.low, arm.input_box.high, (count, arm.nq))


def test_no_payload_no_armature_is_bit_identical() -> None:
    """The defaults load the same URDF text and give the same numbers in torch, numpy and CasADi."""
    arm = load_system("planar3")
    same = dataclasses.replace(arm, payload=None, armature=[])
    assert same.payload is None and same.armature == () and arm.model_urdf == locked_urdf(Path(arm.urdf), arm.joints)
    x, u = states(arm, 8)
    assert np.array_equal(arm.rhs(x, u), same.rhs(x, u))
    xt, ut = torch.from_numpy(x), torch.from_numpy(u)
    assert torch.equal(arm.rhs(xt, ut), same.rhs(xt, ut))
    f, g = arm.casadi_rhs(), same.casadi_rhs()
    assert np.array_equal(np.asarray(f(x[0], u[0])), np.asarray(g(x[0], u[0])))
    m, c = arm.frozen_terms(xt[:, :3], ut)
    m2, c2 = same.frozen_terms(xt[:, :3], ut)
    assert torch.equal(m, m2) and torch.equal(c, c2)


@pytest.mark.parametrize("name", ["planar3", "panda"])
def test_payload_and_armature_match_the_mujoco_robot(name: str) -> None:
    """With the lab robot's payload and armature (no dry friction) the model's rhs in torch, numpy (Pinocchio) and
    CasADi equals MujocoPlant.rhs to 1e-10 of the largest value, scaled masses included; the servo compensates the
    gravity of the arm without the payload, as the robot's does."""
    from pinnmpc.systems import system_config

    arm = load_system(name)
    lab = system_config(name).robots.lab
    robot = {"payload": dict(lab.payload), "armature": list(lab.armature)}
    for mass_scale in (1.0, 1.3):
        nominal = arm.with_mismatch(mass_scale=mass_scale)
        model = dataclasses.replace(nominal, payload=robot["payload"], armature=robot["armature"])
        plant = MujocoPlant(nominal, arm.tau, robot)
        x, u = states(arm, 20)
        ref = np.stack([plant.rhs(xi, ui) for xi, ui in zip(x, u)])
        scale = np.abs(ref).max()
        assert np.abs(model.rhs(x, u) - ref).max() <= 1e-10 * scale
        assert np.abs(model.rhs(torch.from_numpy(x), torch.from_numpy(u)).numpy() - ref).max() <= 1e-10 * scale
        if mass_scale == 1.0:
            f = model.casadi_rhs()
            got = np.stack([np.asarray(f(xi, ui)).ravel() for xi, ui in zip(x[:5], u[:5])])
            assert np.abs(got - ref[:5]).max() <= 1e-10 * scale


def test_bad_payload_and_armature_refused() -> None:
    arm = load_system("planar3")
    with pytest.raises(ValueError, match=r"payload.mass=-1; expected a finite number >= 0"):
        dataclasses.replace(arm, payload={"mass": -1})
    with pytest.raises(ValueError, match=r"armature=\[0.1\]; expected 3 finite numbers >= 0"):
        dataclasses.replace(arm, armature=[0.1])
    with pytest.raises(ValueError, match=r"payload.link='nowhere'"):
        dataclasses.replace(arm, payload=Payload(1.0, None, "nowhere"))


@pytest.fixture(scope="module")
def known_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """12 s of excitation of planar3 with friction 1.2 x the model's and the lab's payload and armature (no dry
    friction), logged 50 times per period."""
    from hydra import compose, initialize_config_dir

    conf = Path(__file__).resolve().parents[1] / "conf"
    known = "{payload: {mass: 0.5, pos: [0.25, 0.0, 0.0]}, armature: [0.03, 0.015, 0.0025]}"
    overrides = ["system=planar3", "plant.robot=known", f"+system.robots.known={known}", "plant.friction_scale=1.2",
                 "robot_time=12", "fine=50", "episodes.kinds=[excitation]", "excitation.duration=6",
                 "progress=false"]  # fmt: skip
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        cfg = compose(config_name="collect", overrides=overrides)
    system = load_system("planar3")
    log = collect(cfg, system, None, None, meta={"robot": "known"})
    stem = tmp_path_factory.mktemp("known") / "robot_log"
    write_log(stem, log)
    return stem.with_suffix(".npz")


def test_identify_recovers_a_known_robot(known_log: Path, tmp_path: Path) -> None:
    """Payload mass within 1 %, viscous and Coulomb friction within 1 %, armature within 8 % (the interval average
    of M, h and the Coulomb term is the fit's only approximation); the fitted system loads from its .yaml."""
    system = load_system("planar3")
    log = read_log(known_log, system)
    assert log.robot_time == pytest.approx(12.0)
    fit = identify(system, [log], ["viscous", "coulomb", "payload", "armature"], Payload(0.0), name="known3",
                   validation_periods=50)  # fmt: skip
    v = fit.values
    assert v["payload_mass"] == pytest.approx(0.5, rel=0.01)
    np.testing.assert_allclose(v["viscous"], [24.0, 9.6, 2.4], rtol=0.01)
    np.testing.assert_allclose(v["coulomb"], [1.2, 0.6, 0.12], rtol=0.01)
    np.testing.assert_allclose(v["armature"], LAB["armature"], rtol=0.08)
    assert all(a < b / 100 for a, b in zip(fit.prediction_rmse, fit.nominal_prediction_rmse))
    from omegaconf import OmegaConf

    from pinnmpc.systems import system_config

    nominal = OmegaConf.to_container(system_config("planar3"), resolve=True)
    path = write_system(tmp_path / "system" / "known3.yaml", system_yaml(nominal, fit, [log.meta], [str(known_log)]))
    loaded = load_system(path)
    assert loaded.name == "known3" and loaded.payload.mass == pytest.approx(0.5, rel=0.01)
    x, u = states(system, 4)
    assert np.abs(loaded.rhs(x, u) - fit.system.rhs(x, u)).max() < 1e-3 * np.abs(fit.system.rhs(x, u)).max()


PANDA_C = (3.0, 4.0, 1.5, 2.0, 0.1, 0.15, 0.02)  # N m: the Panda's servo joint friction a known robot has


def test_servo_coulomb_law_in_every_backend() -> None:
    """A servo's joint friction C tanh(s v): zeros give the nominal numbers bit for bit; otherwise torch, numpy
    (Pinocchio) and CasADi agree and M dv/dt changes by exactly -C tanh(s v); a wrong length is refused."""
    arm = load_system("panda")
    x, u = states(arm, 6)
    zero = dataclasses.replace(arm, coulomb=[0.0] * 7)
    assert np.array_equal(zero.rhs(x, u), arm.rhs(x, u))
    known = dataclasses.replace(arm, coulomb=PANDA_C)
    ref = known.rhs(x, u)
    assert np.abs(known.rhs(torch.from_numpy(x), torch.from_numpy(u)).numpy() - ref).max() <= 1e-10 * np.abs(ref).max()
    f = known.casadi_rhs()
    assert np.abs(np.asarray(f(x[0], u[0])).ravel() - ref[0]).max() <= 1e-10 * np.abs(ref).max()
    m, _, _ = arm.dynamics_terms(torch.from_numpy(x[:, :7]), torch.from_numpy(x[:, 7:]))
    change = np.einsum("bij,bj->bi", m.numpy(), ref[:, 7:] - arm.rhs(x, u)[:, 7:])
    np.testing.assert_allclose(change, -np.asarray(PANDA_C) * np.tanh(arm.coulomb_slope * x[:, 7:]), atol=1e-9)
    with pytest.raises(ValueError, match=r"coulomb=\[1.0\]; expected 7 finite numbers >= 0"):
        dataclasses.replace(arm, coulomb=[1.0])


PANDA_D = (0.3, 0.4, 0.2, 0.2, 0.02, 0.02, 0.005)  # N m s/rad: joint damping a known robot's servos overcome


def test_a_servos_joint_damping_in_every_backend() -> None:
    """A servo's joint damping D v: zeros give the nominal numbers bit for bit; otherwise torch, numpy (Pinocchio)
    and CasADi agree, M dv/dt changes by exactly -D v, and the frozen model's gain is K + D."""
    arm = load_system("panda")
    x, u = states(arm, 6)
    assert np.array_equal(dataclasses.replace(arm, viscous=[0.0] * 7).rhs(x, u), arm.rhs(x, u))
    damped = dataclasses.replace(arm, viscous=PANDA_D)
    ref = damped.rhs(x, u)
    assert np.abs(damped.rhs(torch.from_numpy(x), torch.from_numpy(u)).numpy() - ref).max() <= 1e-10 * np.abs(ref).max()
    assert np.abs(np.asarray(damped.casadi_rhs()(x[0], u[0])).ravel() - ref[0]).max() <= 1e-10 * np.abs(ref).max()
    m, _, _ = arm.dynamics_terms(torch.from_numpy(x[:, :7]), torch.from_numpy(x[:, 7:]))
    change = np.einsum("bij,bj->bi", m.numpy(), ref[:, 7:] - arm.rhs(x, u)[:, 7:])
    np.testing.assert_allclose(change, -np.asarray(PANDA_D) * x[:, 7:], atol=1e-9)
    np.testing.assert_allclose(damped.linear_gain, np.add(arm.servo_gain, PANDA_D))


def test_a_servo_that_compensates_coriolis_too_in_every_backend() -> None:
    """servo_compensation='bias' (franky-sim's joint velocity controller): M dv/dt = K (u - v) for the arm alone,
    the same in torch, numpy (Pinocchio), CasADi and MuJoCo, and with a payload torch and numpy agree; the arm's
    ArmPrior holds no Coriolis torque then; an unknown compensation is refused in one line."""
    from pinnmpc.surrogate.prior import ArmPrior

    arm = dataclasses.replace(load_system("panda"), servo_compensation="bias")
    x, u = states(arm, 6)
    ref = arm.rhs(x, u)
    m, _, _ = arm.dynamics_terms(torch.from_numpy(x[:, :7]), torch.from_numpy(x[:, 7:]))
    law = np.linalg.solve(m.numpy(), (np.asarray(arm.servo_gain) * (u - x[:, 7:]))[..., None])[..., 0]
    np.testing.assert_allclose(ref[:, 7:], law, rtol=1e-9, atol=1e-9 * np.abs(law).max())
    assert np.abs(arm.rhs(torch.from_numpy(x), torch.from_numpy(u)).numpy() - ref).max() <= 1e-10 * np.abs(ref).max()
    assert np.abs(np.asarray(arm.casadi_rhs()(x[0], u[0])).ravel() - ref[0]).max() <= 1e-10 * np.abs(ref).max()
    mujoco = np.array([MujocoPlant(arm, arm.tau).rhs(xi, ui) for xi, ui in zip(x, u)])
    assert np.abs(mujoco - ref).max() <= 1e-6 * np.abs(ref).max()
    assert np.abs(load_system("panda").rhs(x, u) - ref).max() > 1e-3 * np.abs(ref).max()  # gravity alone differs
    loaded = dataclasses.replace(arm, payload=Payload(0.5, (0.0, 0.0, 0.05)))
    both = loaded.rhs(x, u), loaded.rhs(torch.from_numpy(x), torch.from_numpy(u)).numpy()
    assert np.abs(both[0] - both[1]).max() <= 1e-9 * np.abs(both[0]).max()
    assert not ArmPrior(arm, "midpoint_arm").coriolis and ArmPrior(load_system("panda"), "midpoint_arm").coriolis
    with pytest.raises(ValueError, match=r"servo_compensation='all'; expected one of \['gravity', 'bias'\]"):
        dataclasses.replace(arm, servo_compensation="all")


def excited_panda_log(tmp_path: Path, robot: RigidArm) -> RobotLog:
    """8 s of excitation of a Panda robot (at fine = 20), as read back for the nominal Panda."""
    from hydra import compose, initialize_config_dir

    conf = Path(__file__).resolve().parents[1] / "conf"
    overrides = ["system=panda", "robot_time=8", "fine=20", "episodes.kinds=[excitation]", "excitation.duration=4",
                 "progress=false"]  # fmt: skip
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        cfg = compose(config_name="collect", overrides=overrides)
    write_log(tmp_path / "robot_log", collect(cfg, robot, None, None, meta={"robot": None}))
    return read_log(tmp_path / "robot_log.npz", load_system("panda"))


def test_identify_recovers_a_servos_joint_friction(tmp_path: Path) -> None:
    """A Panda whose servos fight known joint friction, excited for 8 s: the fit recovers the servo gains and that
    friction within 3 % from the nominal model, which has none."""
    nominal = load_system("panda")
    log = excited_panda_log(tmp_path, dataclasses.replace(nominal, coulomb=PANDA_C))
    fit = identify(nominal, [log], ["servo_gain", "coulomb"], validation_periods=20, rk4_steps=20)
    np.testing.assert_allclose(fit.values["servo_gain"], nominal.servo_gain, rtol=0.03)
    np.testing.assert_allclose(fit.values["coulomb"], PANDA_C, rtol=0.03)


def test_identify_recovers_a_servos_joint_damping_beside_its_friction(tmp_path: Path) -> None:
    """A Panda whose servos fight known joint damping and friction, excited for 8 s: with the gains kept, the fit
    recovers the friction within 5 % on every joint and the damping within 10 % on joints 2 and 4-7 (8 s of
    excitation leaves joints 1 and 3's apart from their friction less well); without the damping column the wrist's
    friction comes out high (it takes up the damping at the excitation's speeds)."""
    nominal = load_system("panda")
    log = excited_panda_log(tmp_path, dataclasses.replace(nominal, coulomb=PANDA_C, viscous=PANDA_D))
    fit = identify(nominal, [log], ["viscous", "coulomb"], validation_periods=20, rk4_steps=50)
    np.testing.assert_allclose(fit.values["coulomb"], PANDA_C, rtol=0.05)
    observed = [1, 3, 4, 5, 6]
    np.testing.assert_allclose(np.asarray(fit.values["viscous"])[observed], np.asarray(PANDA_D)[observed], rtol=0.1)
    assert fit.prediction_rmse[7] < 0.1 * fit.nominal_prediction_rmse[7]  # its steps follow the robot's
    without = identify(nominal, [log], ["coulomb"], validation_periods=20, rk4_steps=50)
    high = np.asarray(without.values["coulomb"])[4:] / PANDA_C[4:] - 1
    assert high.min() > 0.04, high


def test_place_columns_are_exact_anywhere(known_log: Path) -> None:
    """The unit-mass column the quadratic gives at a place off the stencil equals the arm's own at that place."""
    from pinnmpc.robot_data.identify import _bare, _interval_terms, _unit_column, intervals, place_columns

    system = load_system("panda")
    s = intervals([read_log(known_log, load_system("planar3"))], max_samples=40)  # planar3's states: 3 of 7 joints
    rng = np.random.default_rng(1)
    s = dataclasses.replace(s, q=rng.uniform(-1, 1, (40, 2, 7)), v=rng.uniform(-1, 1, (40, 2, 7)), u=np.zeros((40, 7)))
    link, c0, column = place_columns(system, s, Payload(0.0), 0.1)
    assert link == "panda_hand_tcp" and np.array_equal(c0, np.zeros(3))
    c = np.array([0.03, -0.17, -0.11])
    m0, h0, _ = _interval_terms(_bare(system), s)
    direct = _unit_column(_bare(system), s, Payload(1.0, tuple(c), link), m0, h0).reshape(-1)
    assert np.abs(column(c) - direct).max() <= 1e-9 * np.abs(direct).max()


def test_identify_finds_where_a_payload_sits(tmp_path: Path) -> None:
    """A Panda carrying 1 kg at its flange, 0.1034 m behind the tool centre point where the search starts: the fit
    finds the place within 5 mm and the mass within 2 %; held at the start, the mass comes out wrong."""
    from hydra import compose, initialize_config_dir

    conf = Path(__file__).resolve().parents[1] / "conf"
    overrides = ["system=panda", "plant.robot=flange", "+system.robots.flange={payload: {mass: 1.0, pos: [0, 0, "
                 "-0.1034]}}", "robot_time=8", "fine=20", "episodes.kinds=[excitation]", "excitation.duration=4",
                 "progress=false"]  # fmt: skip
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        cfg = compose(config_name="collect", overrides=overrides)
    nominal = load_system("panda")
    write_log(tmp_path / "robot_log", collect(cfg, nominal, None, None, meta={"robot": "flange"}))
    log = read_log(tmp_path / "robot_log.npz", nominal)
    fit = identify(nominal, [log], ["payload", "payload_pos"], validation_periods=20, rk4_steps=20)
    assert fit.values["payload_mass"] == pytest.approx(1.0, rel=0.02)
    np.testing.assert_allclose(fit.values["payload_pos"], [0.0, 0.0, -0.1034], atol=5e-3)
    assert fit.system.payload.link == "panda_hand_tcp"
    held = identify(nominal, [log], ["payload"], validation_periods=0)
    assert held.values["payload_mass"] < 0.8
    with pytest.raises(ValueError, match=r"fit.payload_pos=true needs fit.payload=true"):
        identify(nominal, [log], ["payload_pos"])


def test_the_identify_command_reports_and_writes_the_place(known_log: Path, tmp_path: Path) -> None:
    """`python -m pinnmpc.identify` names the payload's fitted place in its summary and writes it into the system
    .yaml, which loads with the load where the robot carries it."""
    import subprocess
    import sys

    out = tmp_path / "system" / "known3.yaml"
    args = ["system=planar3", f"logs=[{known_log}]", f"out={out}", "validation_periods=20", "rk4_steps=20",
            "max_samples=3000", f"hydra.run.dir={tmp_path / 'run'}"]  # fmt: skip
    done = subprocess.run([sys.executable, "-m", "pinnmpc.identify", *args], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    assert " kg at [0.25" in done.stdout
    loaded = load_system(out)
    np.testing.assert_allclose(loaded.payload.pos, LAB["payload"]["pos"], atol=5e-3)
    assert loaded.payload.link == "link3"


def test_identify_says_when_the_robot_is_outside_the_models_class(known_log: Path, tmp_path: Path) -> None:
    """In class (the known robot) the fit leaves well under class_residual of each joint's torque scale; on the
    shop robot (Stribeck and load friction, droop, cogging, lag) it leaves more, and fit.json and the warnings say
    the robot is outside the model's class."""
    from hydra import compose, initialize_config_dir

    from pinnmpc.robot_data.identify_job import run_identify

    conf = Path(__file__).resolve().parents[1] / "conf"
    collect_overrides = ["system=planar3", "plant.robot=shop", "robot_time=12", "fine=10",
                         "episodes.kinds=[excitation]", "excitation.duration=6", "progress=false"]  # fmt: skip
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        shop_cfg = compose(config_name="collect", overrides=collect_overrides)
    stem = tmp_path / "shop" / "robot_log"
    stem.parent.mkdir()
    write_log(stem, collect(shop_cfg, load_system("planar3"), None, None, meta={"robot": "shop"}))
    for log, outside in ((known_log, False), (stem.with_suffix(".npz"), True)):
        run = tmp_path / ("out" if outside else "in")
        overrides = ["system=planar3", f"logs=[{log}]", f"out={run / 'fit.yaml'}", "validation_periods=20",
                     "rk4_steps=20", "max_samples=3000"]  # fmt: skip
        with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
            cfg = compose(config_name="identify", overrides=overrides)
        result = run_identify(cfg, run)
        assert result["outside_class"] is outside, result["residual_fraction"]
        assert (max(result["residual_fraction"]) > cfg.class_residual) is outside
        said = any("outside the model's class" in w for w in result["warnings"])
        assert said is outside and json.loads((run / "fit.json").read_text())["outside_class"] is outside


def test_settle_leaves_out_the_ramp_after_each_command(tmp_path: Path) -> None:
    """A Panda whose servo demand follows each command through a first-order lag (as franky ramps a Franka's): the
    fit over every interval mistakes the ramp for weak gains; leaving out the first intervals of each period
    (settle, 10 lag times) recovers them within 1 %; a settle of the whole period is refused in one line."""
    from hydra import compose, initialize_config_dir

    conf = Path(__file__).resolve().parents[1] / "conf"
    overrides = ["system=panda", "robot_time=8", "fine=20", "episodes.kinds=[excitation]", "excitation.duration=4",
                 "progress=false", "plant.robot=ramp", "+system.robots.ramp.lag=0.002"]  # fmt: skip
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        cfg = compose(config_name="collect", overrides=overrides)
    nominal = load_system("panda")
    write_log(tmp_path / "robot_log", collect(cfg, nominal, None, None, meta={"robot": "ramp"}))
    log = read_log(tmp_path / "robot_log.npz", nominal)
    gains = {s: identify(nominal, [log], ["servo_gain"], validation_periods=0, settle=s).values["servo_gain"]
             for s in (0.0, 0.02)}  # fmt: skip
    assert np.abs(np.asarray(gains[0.0]) / nominal.servo_gain - 1).max() > 0.05  # measured: 3-9 % low
    np.testing.assert_allclose(gains[0.02], nominal.servo_gain, rtol=0.01)
    with pytest.raises(ValueError, match=r"settle=0.05; expected 0 <= settle < the control period 0.05 s"):
        identify(nominal, [log], ["servo_gain"], validation_periods=0, settle=0.05)


def test_a_load_the_servo_compensates_shows_only_its_inertia() -> None:
    """load (a Franka's configured hand): M is the arm's with that point mass, as with it as a payload, in torch,
    numpy and CasADi alike; its gravity and Coriolis torques are the servo's, so at v = u the arm does not
    accelerate, where the same mass as a payload sags; a bad load is refused in one line."""
    arm = dataclasses.replace(load_system("fr3"), armature=())
    hand = Payload(0.73, (-0.01, 0.0, 0.03), "link8")
    loaded, carried = dataclasses.replace(arm, load=hand), dataclasses.replace(arm, payload=hand)
    x, _ = states(arm, 6)
    q, v = torch.from_numpy(x[:, :7]), torch.from_numpy(x[:, 7:])
    m_load, m_payload, m_arm = (a.dynamics_terms(q, v)[0] for a in (loaded, carried, arm))
    assert torch.allclose(m_load, m_payload, rtol=1e-12) and not torch.allclose(m_load, m_arm, rtol=1e-3)
    u = x[:, 7:]  # at v = u the servo's K (u - v) is zero
    rest = loaded.rhs(x, u)
    assert np.abs(rest[:, 7:]).max() < 1e-9
    assert np.abs(carried.rhs(x, u)[:, 7:]).max() > 0.1
    y, w = states(arm, 4, seed=1)
    ref = loaded.rhs(y, w)
    assert np.abs(loaded.rhs(torch.from_numpy(y), torch.from_numpy(w)).numpy() - ref).max() <= 1e-9 * np.abs(ref).max()
    got = np.asarray(loaded.casadi_rhs()(y[0], w[0])).ravel()
    assert np.abs(got - ref[0]).max() <= 1e-9 * np.abs(ref).max()
    with pytest.raises(ValueError, match=r"fr3: load.mass=-1; expected a finite number >= 0"):
        dataclasses.replace(arm, load={"mass": -1})


def test_identify_by_the_reported_command_needs_logs_that_have_it(known_log: Path) -> None:
    """command=reported on a log without the robot's reported commands (a MuJoCo robot's) is refused in one line, as
    is an unknown command."""
    system = load_system("planar3")
    log = read_log(known_log, system)
    with pytest.raises(ValueError, match=r"command=reported: log 0 has no reported commands \(command_fine"):
        identify(system, [log], ["armature"], validation_periods=0, command="reported")
    with pytest.raises(ValueError, match=r"command='late'; expected one of \['held', 'reported'\]"):
        identify(system, [log], ["armature"], validation_periods=0, command="late")
