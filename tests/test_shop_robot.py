"""Robots with effects outside the identification's class (pinnmpc/plant/effects.py): each applied effect acts as its
law says, the actuator lag carries its state from one period to the next, and the shipped `shop` robots are sized
against the input box by inverse dynamics and differ from the model as issue 65 asks."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from omegaconf import OmegaConf

pytest.importorskip("mujoco")
pytest.importorskip("pinocchio")

from pinnmpc import load_system  # noqa: E402 (after the skips)
from pinnmpc.plant.effects import EffectLaw, robot_effects  # noqa: E402
from pinnmpc.plant.mujoco_robot import MujocoPlant, input_demand, make_mujoco_plant  # noqa: E402
from pinnmpc.references.builtin import builtin_reference  # noqa: E402
from pinnmpc.systems import system_config  # noqa: E402

SIZED = {  # the references each shop robot is sized for (planar3's others need 0.96-1.02 of the box on the model)
    "planar3": ["default", "random-101", "random-105"],
    "panda": ["default", "random", "driven", "random-101", "random-105"],
}


def shop(name: str) -> dict[str, Any]:
    """The arm's shop robot from its config, as plain data."""
    return OmegaConf.to_container(system_config(name).robots.shop, resolve=True)


def references(name: str, names: list[str]) -> list[Any]:
    """Built-in references of the arm by name, on their fine grid."""
    system, cfg = load_system(name), system_config(name)
    specs = OmegaConf.to_container(cfg.references, resolve=True)
    box = (system.state_box.low[: system.nq], system.state_box.high[: system.nq])
    return [builtin_reference(r, specs, box, system) for r in names]


@pytest.mark.parametrize("name", sorted(SIZED))
def test_the_shop_robot_needs_at_most_095_of_the_input_box(name: str) -> None:
    """Inverse dynamics on the shop robot (payload, frictions, droop, cogging, the lag's u + T du/dt) along every
    reference it is sized for: at most 0.95 of the input box, and more than on the model (its effects cost input)."""
    system = load_system(name)
    robot, model = MujocoPlant(system, system.tau, shop(name)), MujocoPlant(system, system.tau)
    for ref in references(name, SIZED[name]):
        need, nominal = input_demand(robot, ref.t, ref.x).max(), input_demand(model, ref.t, ref.x).max()
        assert nominal < need <= 0.95, f"{ref.name}: {need:.3f} of the box on shop, {nominal:.3f} on the model"


@pytest.mark.parametrize("name", sorted(SIZED))
def test_the_needed_input_gives_the_acceleration(name: str) -> None:
    """needed_input inverts the robot's forward dynamics (its effects and actuation law) at random states: exactly
    without MuJoCo's dry-friction constraint, and with it where every joint moves (|v| >= 0.2 rad/s: the constraint's
    force is the Coulomb level there; slower, it holds less, which inverse dynamics cannot know)."""
    system = load_system(name)
    robot = shop(name)
    plants = (MujocoPlant(system, system.tau, {**robot, "frictionloss": None}), MujocoPlant(system, system.tau, robot))
    rng = np.random.default_rng(1)
    for plant, tol in zip(plants, (1e-9, 1e-6)):
        for _ in range(20):
            x = rng.uniform(system.state_box.low, system.state_box.high) * 0.5
            q, v = x[: system.nq], x[system.nq :]
            v = np.sign(v) * np.maximum(np.abs(v), 0.2)
            a = rng.uniform(-1.0, 1.0, system.nq)
            np.testing.assert_allclose(plant.acceleration(q, v, plant.needed_input(q, v, a)), a, atol=tol)


def test_each_applied_effect_acts_as_its_law_says() -> None:
    """Joint force of each effect alone, at chosen states: Stribeck fades with speed, load friction grows with the
    torque, droop scales the motor by 1 - |v| / droop_speed, cogging repeats every cogging_period."""
    joints = ("a", "b")
    law = EffectLaw(robot_effects({"stribeck": [1.0, 0.0], "stribeck_speed": 0.1}, joints))
    q, motor = np.zeros(2), np.zeros(2)
    slow, fast = law.joint_force(q, np.array([0.05, 0.05]), motor), law.joint_force(q, np.array([0.5, 0.5]), motor)
    assert slow[0] < -0.5 and abs(fast[0]) < 1e-9 and slow[1] == 0.0  # resists slow motion, gone at 5 x the speed
    law = EffectLaw(robot_effects({"load_friction": [0.1, 0.1]}, joints))
    v = np.array([1.0, -1.0])
    np.testing.assert_allclose(law.joint_force(q, v, np.array([10.0, 10.0])), [9.0, 11.0], rtol=1e-6)
    law = EffectLaw(robot_effects({"droop_speed": [2.0, 0.0]}, joints))
    np.testing.assert_allclose(law.joint_force(q, v, np.array([10.0, 10.0])), [5.0, 10.0])  # joint b: no droop
    law = EffectLaw(robot_effects({"cogging": [0.5, 0.0], "cogging_period": 0.2}, joints))
    f = [law.joint_force(np.array([p, 0.0]), np.zeros(2), motor)[0] for p in (0.05, 0.25, 0.15)]
    np.testing.assert_allclose(f, [-0.5, -0.5, 0.5], atol=1e-12)


def test_the_lag_carries_its_state_between_periods() -> None:
    """With an actuator lag a step from the last step's end continues the filter (the input ramps in again only
    partly), a lone step starts it settled; without a lag both are the same step."""
    system = load_system("planar3")
    x0, u0, u1 = np.zeros(6), np.array([30.0, 10.0, 2.0]), np.array([-30.0, -10.0, -2.0])
    lagged = MujocoPlant(system, system.tau, {"lag": 0.05})
    x1 = lagged.step(x0, u0)
    continued = lagged.step(x1, u1)
    lone = MujocoPlant(system, system.tau, {"lag": 0.05}).step(x1, u1)
    assert np.abs(continued - lone).max() > 1e-3  # the filter still held u0 at the start
    again = MujocoPlant(system, system.tau, {"lag": 0.05}).step(x1, u1)
    np.testing.assert_array_equal(lone, again)  # a lone step is a function of (x, u): the filter settled at u
    plain = MujocoPlant(system, system.tau)
    np.testing.assert_allclose(plain.step(x1, u1), lone, rtol=0, atol=1e-12)


def test_a_period_from_a_given_actuator_state_is_the_robots_own_and_leaves_the_loops() -> None:
    """period_from predicts a period of the robot with the lag's filter where it is told (settled at u: a lone step's),
    and a closed loop's filter state carries on past it as if it had not been called."""
    system = load_system("planar3")
    x0, u0, u1 = np.zeros(6), np.array([30.0, 10.0, 2.0]), np.array([-30.0, -10.0, -2.0])
    loop, fresh = (MujocoPlant(system, system.tau, {"lag": 0.05}) for _ in range(2))
    x1 = loop.step(x0, u0)
    np.testing.assert_array_equal(loop.period_from(x0, u0, u0), x1)  # settled at u0: the lone step
    from_zero = loop.period_from(x0, u0, 0 * u0)
    assert np.abs(from_zero - x1).max() > 1e-3  # the filter told to start elsewhere: another period
    np.testing.assert_array_equal(loop.step(x1, u1), fresh.step(fresh.step(x0, u0), u1))  # the loop's filter kept


@pytest.mark.parametrize(
    "robot, says",
    [
        ({"stribeck_speed": 0.0}, r"robot stribeck_speed=0.0; expected a finite number > 0 \(rad/s\)"),
        ({"lag": -0.01}, r"robot lag=-0.01; expected a finite number >= 0 \(s\)"),
        ({"droop_speed": [1.0, 2.0]}, r"robot droop_speed=\[1.0, 2.0\]; expected 3 finite numbers >= 0 \(rad/s\)"),
        ({"cogging": [0.1, 0.1, -0.1]}, r"robot cogging=.*expected 3 finite numbers >= 0 \(N m\)"),
        ({"backlash": 0.1}, r"robot keys \['backlash'\]; expected some of"),
    ],
)
def test_a_bad_effect_is_one_line(robot: dict[str, Any], says: str) -> None:
    system = load_system("planar3")
    with pytest.raises(ValueError, match=f"system.robots.bad: {says}") as err:
        make_mujoco_plant(system, system.tau, {"bad": robot}, "bad")
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("name", ["planar3", pytest.param("panda", marks=pytest.mark.slow)])
def test_the_nominal_classical_nmpc_tracks_5x_worse_on_shop_and_its_monitor_says_why(make_cfg, tmp_path, name) -> None:
    """The classical NMPC on the nominal model (the arm's default settings) in a real closed loop: on the shop robot
    its worst joint-angle MAE is at least 5x the one on the nominal MuJoCo arm, and its model monitor says the model
    does not fit there (and fits on the model)."""
    from pinnmpc.simulation.run import run_closed_loop

    common = [f"system={name}", "controller=casadi", "plant=mujoco", "max_steps=80", "progress=false", "plots=false"]
    runs = {}
    for robot in ("null", "shop"):
        runs[robot] = run_closed_loop(make_cfg("closed_loop", [*common, f"plant.robot={robot}"]), tmp_path / robot)
    worst = {k: max(v for j, v in m["mae"].items() if j.startswith("q_")) for k, m in runs.items()}
    assert all(m["status"] == "ok" for m in runs.values())
    assert worst["shop"] >= 5 * worst["null"], worst
    assert runs["null"]["model_fits"] is True and runs["shop"]["model_fits"] is False


def test_the_shipped_shop_network_knows_its_robot_and_tracks_closer_there(make_cfg, tmp_path) -> None:
    """planar3-shop.pt: fine-tuned on shop logs (its meta names the robot and the command), it tracks the shop robot
    with the estimator at least 3x closer than the nominal planar3.pt does (6.6x measured over 80 samples)."""
    from pinnmpc.simulation.run import run_closed_loop
    from pinnmpc.surrogate.checkpoint import CHECKPOINTS, load_surrogate

    net = load_surrogate(CHECKPOINTS / "planar3-shop.pt")
    assert [log["robot"] for log in net.meta["robot_logs"]] == ["shop"]
    assert "experiment=planar3-shop" in net.meta["provenance"][-1]["command"]
    assert net.meta["previous_input"] and net.input_names[3:] == ("u_joint1_prev", "u_joint2_prev", "u_joint3_prev")
    common = ["system=planar3", "plant=mujoco", "plant.robot=shop", "max_steps=80", "progress=false", "plots=false"]
    worst = {}
    for name in ("planar3-shop", "planar3"):
        m = run_closed_loop(
            make_cfg("closed_loop", [*common, f"checkpoint={CHECKPOINTS / f'{name}.pt'}"]), tmp_path / name
        )
        assert m["status"] == "ok"
        worst[name] = max(v for k, v in m["mae"].items() if k.startswith("q_"))
    assert worst["planar3-shop"] * 3 <= worst["planar3"], worst
