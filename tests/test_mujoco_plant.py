"""plant=mujoco: MuJoCo simulates the arm's URDF exactly as the model when nominal, and measurably otherwise."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from scipy.integrate import solve_ivp

pytest.importorskip("mujoco")
pin = pytest.importorskip("pinocchio")

from pinnmpc import load_system  # noqa: E402 (after the skips)
from pinnmpc.plant import PlantError, ScipyPlant  # noqa: E402
from pinnmpc.plant.mujoco_robot import MujocoPlant, make_mujoco_plant  # noqa: E402
from pinnmpc.simulation.run import run_closed_loop  # noqa: E402
from pinnmpc.systems import RigidArm, system_config  # noqa: E402

ARMS = ("planar3", "panda")


@pytest.fixture(scope="module", params=ARMS)
def arm(request: pytest.FixtureRequest) -> RigidArm:
    """Each URDF arm with a `robots` block."""
    return load_system(request.param)


def lab(system: RigidArm) -> dict[str, Any]:
    """The arm's `lab` robot from its config, as plain data."""
    robot = system_config(system.name).robots.lab
    return {"payload": dict(robot.payload), "armature": list(robot.armature), "frictionloss": list(robot.frictionloss)}


def samples(system: RigidArm, count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Random states and inputs in the system's boxes."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(system.state_box.low, system.state_box.high, (count, 2 * system.nq))
    u = rng.uniform(system.input_box.low, system.input_box.high, (count, system.nq))
    return x, u


@pytest.mark.parametrize("scales", [(1.0, 1.0), (0.8, 1.3)], ids=["nominal", "scaled"])
def test_accelerations_match_the_model(arm: RigidArm, scales: tuple[float, float]) -> None:
    """MuJoCo's dv/dt on 200 states equals the model's (Pinocchio ABA) to 1e-10 of the largest acceleration."""
    system = arm.with_mismatch(friction_scale=scales[0], mass_scale=scales[1])
    plant = MujocoPlant(system, system.tau)
    x, u = samples(system, 200)
    ref = system.rhs(x, u)
    got = np.stack([plant.rhs(xi, ui) for xi, ui in zip(x, u)])
    assert np.abs(got - ref).max() <= 1e-10 * np.abs(ref).max()


def test_payload_and_armature_are_exact(arm: RigidArm) -> None:
    """The lab robot without friction is the rigid model plus a point mass at the tip and armature on M's diagonal
    (checked by Pinocchio with the payload added to the last joint's inertia); the servo compensates nominal gravity."""
    robot = lab(arm)
    plant = MujocoPlant(arm, arm.tau, {"payload": robot["payload"], "armature": robot["armature"]})
    model, data = arm.pinocchio
    heavy = model.copy()
    tip = heavy.frames[heavy.getFrameId(arm.tip_frame)].placement if arm.tip_frame else pin.SE3.Identity()
    centre = tip.act(np.asarray(robot["payload"]["pos"], dtype=float))
    heavy.inertias[arm.nq] = heavy.inertias[arm.nq] + pin.Inertia(robot["payload"]["mass"], centre, np.zeros((3, 3)))
    hdata = heavy.createData()
    for xi, ui in zip(*samples(arm, 50, seed=1)):
        q, v = xi[: arm.nq], xi[arm.nq :]
        torque = arm.actuation_torque(v, ui)
        if arm.actuation == "velocity_servo":
            torque = torque + pin.computeGeneralizedGravity(model, data, q)
        m = pin.crba(heavy, hdata, q)
        m = np.triu(m) + np.triu(m, 1).T + np.diag(robot["armature"])
        ref = np.linalg.solve(m, torque - pin.nonLinearEffects(heavy, hdata, q, v))
        assert np.abs(plant.acceleration(q, v, ui) - ref).max() <= 1e-10 * np.abs(ref).max()


def test_nominal_step_is_as_accurate_as_the_scipy_plant(arm: RigidArm) -> None:
    """One period of the default RK4 lands at least as close to a tight solve_ivp as the RK45 plant (rtol 1e-3)."""
    x, u = samples(arm, 4, seed=2)
    x[:2, arm.nq :] = 0.0  # from rest too: planar3's smoothed Coulomb term is stiffest there
    mujoco_plant, scipy_plant = MujocoPlant(arm, arm.tau), ScipyPlant(arm, arm.tau)
    worst = {"mujoco": np.zeros(2), "scipy": np.zeros(2)}
    for xi, ui in zip(x, u):
        exact = solve_ivp(
            lambda _t, y, w: arm.rhs(y, w), (0.0, arm.tau), xi, method="DOP853", args=(ui,), rtol=1e-11, atol=1e-11
        )
        for key, plant in (("mujoco", mujoco_plant), ("scipy", scipy_plant)):
            err = np.abs(plant.step(xi, ui) - exact.y[:, -1])
            worst[key] = np.maximum(worst[key], [err[: arm.nq].max(), err[arm.nq :].max()])
    assert np.all(worst["mujoco"] <= worst["scipy"]), worst
    assert np.all(worst["mujoco"] <= [1e-4, 1e-3]), worst
    assert len(mujoco_plant.step_times) == 4 and mujoco_plant.stick_slip_steps == 0


def test_lab_robot_differs_and_each_effect_counts(arm: RigidArm) -> None:
    """From rest the lab robot's step differs from the nominal one, and payload, armature and frictionloss each
    change a step from a moving state; the plant is a pure function of (x, u)."""
    robot = lab(arm)
    nominal = MujocoPlant(arm, arm.tau)
    lab_plant = make_mujoco_plant(arm, arm.tau, system_config(arm.name).robots, "lab")
    x, u = samples(arm, 1, seed=3)
    rest = np.concatenate((x[0, : arm.nq], np.zeros(arm.nq)))
    assert np.abs(lab_plant.step(rest, 0.3 * u[0]) - nominal.step(rest, 0.3 * u[0]))[arm.nq :].max() > 1e-2
    base = nominal.step(x[0], u[0])
    for key in ("payload", "armature", "frictionloss"):
        alone = MujocoPlant(arm, arm.tau, {key: robot[key]}).step(x[0], u[0])
        assert np.abs(alone - base)[arm.nq :].max() > 1e-3, key
    again = lab_plant.step(x[0], u[0])
    lab_plant.step(rest, u[0])
    np.testing.assert_array_equal(lab_plant.step(x[0], u[0]), again)


BAD_ROBOTS = [
    ({"mass": 1.0}, "robot keys ['mass']"),
    ({"payload": {"mass": -1.0}}, "payload.mass=-1.0"),
    ({"payload": {"mass": 1.0, "where": "tip"}}, "payload="),
    ({"payload": {"pos": [0, 0, 0]}}, "payload="),
    ({"payload": {"mass": 1.0, "pos": [0, 0]}}, "payload.pos=[0, 0]"),
    ({"armature": [0.1]}, "armature=[0.1]"),
    ({"armature": [0.1, 0.1, -0.1]}, "armature=[0.1, 0.1, -0.1]"),
    ({"frictionloss": [0.1, float("nan"), 0.1]}, "frictionloss=[0.1, nan, 0.1]"),
    ({"frictionloss": "high"}, "frictionloss='high'"),
]


@pytest.mark.parametrize(("robot", "says"), BAD_ROBOTS)
def test_bad_robots_fail_in_one_line(robot: dict[str, Any], says: str) -> None:
    """A robot description the plant cannot use is refused at construction, naming the key and the value."""
    system = load_system("planar3")
    with pytest.raises(ValueError) as caught:
        MujocoPlant(system, system.tau, robot)
    message = str(caught.value)
    assert says in message and "expected" in message and "\n" not in message


def test_robot_names_and_step_errors() -> None:
    """An unknown robot name lists the known ones; a bad input or state raises PlantError, not garbage."""
    system = load_system("planar3")
    with pytest.raises(ValueError, match=r"plant.robot='lap'; expected null or one of \['lab', 'shop'\]"):
        make_mujoco_plant(system, system.tau, system_config("planar3").robots, "lap")
    with pytest.raises(ValueError, match="system.robots.bad: robot armature"):
        make_mujoco_plant(system, system.tau, {"bad": {"armature": [1.0]}}, "bad")
    with pytest.raises(ValueError, match="substeps=0"):
        MujocoPlant(system, system.tau, substeps=0)
    with pytest.raises(ValueError, match="URDF arm"):
        MujocoPlant(load_system("powercube"), 0.2)
    plant = make_mujoco_plant(system, system.tau, None, None, friction_scale=1.2)
    assert plant.system.friction_scale == 1.2
    with pytest.raises(PlantError, match="non-finite"):
        plant.step(np.full(6, np.nan), np.zeros(3))
    with pytest.raises(PlantError, match="shape"):
        plant.step(np.zeros(6), np.zeros(2))


def test_a_closed_loop_on_the_nominal_mujoco_robot_tracks_as_on_the_model(make_cfg, tmp_path) -> None:
    # the same controller on both plants, the scipy plant at tight tolerances: the MuJoCo plant is the model
    common = ["system=planar3", "max_steps=30", "progress=false", "plots=false", "controller.disturbance.gain=0"]
    tight = run_closed_loop(make_cfg("closed_loop", [*common, "plant.rtol=1e-9", "plant.atol=1e-11"]), tmp_path / "a")
    robot = run_closed_loop(make_cfg("closed_loop", [*common, "plant=mujoco", "plant.substeps=200"]), tmp_path / "b")
    assert tight["status"] == robot["status"] == "ok" and robot["plant"] == {"kind": "mujoco", "robot": None}
    for joint in ("q_joint1", "q_joint2", "q_joint3"):
        assert robot["mae"][joint] == pytest.approx(tight["mae"][joint], rel=0.01), joint
    lab = make_cfg("closed_loop", [*common, "plant=mujoco", "plant.robot=lab"])
    assert run_closed_loop(lab, tmp_path / "c")["mae"]["q_joint3"] > 3 * robot["mae"]["q_joint3"]  # a real mismatch
    with pytest.raises(ValueError, match=r"plant.robot='nope'; expected null or one of \['lab', 'shop'\]"):
        run_closed_loop(make_cfg("closed_loop", [*common, "plant=mujoco", "plant.robot=nope"]), tmp_path / "d")
