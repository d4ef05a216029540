"""A network that takes the previous input: real logs of a lagging MuJoCo robot, real Lightning training on them, the
real controller on that robot."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from pinnmpc import load_surrogate, load_system
from pinnmpc.controller.build import build_nmpc
from pinnmpc.controller.previous_input import PreviousInputNMPC, padded_weight
from pinnmpc.plant.mujoco_robot import make_mujoco_plant
from pinnmpc.references import Reference
from pinnmpc.robot_data.episodes import transitions
from pinnmpc.robot_data.logs import read_log
from pinnmpc.simulation.loop import run_loop
from pinnmpc.surrogate.checkpoint import Surrogate
from pinnmpc.surrogate.previous_input import PreviousInputFlow
from pinnmpc.systems.previous_input import WithPreviousInput, takes_previous_input
from pinnmpc.systems.registry import system_config
from pinnmpc.training.grow import widened
from pinnmpc.training.run import train
from tests.conftest import TINY_TRAIN, write_test_log

FINE = 10  # samples per control period in the test log
TINY = [*TINY_TRAIN, "system=planar3", "model.auto_scale.h=1e-3", "progress=false", "data.n_anchor=0"]
LAG_ONLY = {"lag": 0.02}  # planar3's shop robot's actuator lag (a fifth of the period), alone


def _robot(effects: dict, fine: int = 1, substeps: int = 20) -> object:
    """planar3 in MuJoCo with the given effects, stepped `fine` times per period by `substeps` RK4 steps each."""
    system = load_system("planar3")
    return make_mujoco_plant(system, system.tau / fine, {"lagging": effects}, "lagging", substeps=substeps)


@pytest.fixture(scope="module")
def lag_log(tmp_path_factory) -> str:
    """Five 6-s episodes of planar3 with a lagging actuator under random piecewise-constant inputs, as
    `pinnmpc.collect` writes them (control rate and FINE samples per period)."""
    system = load_system("planar3")
    plant = _robot(LAG_ONLY, FINE, substeps=2)  # RK4 at 5 ms: a quarter of the lag's time constant
    rng = np.random.default_rng(0)
    high = 0.5 * np.asarray(system.input_box.high)
    coarse, fine, steps = [], [], 60
    for ep in range(5):
        x, t0 = np.zeros(6), 10.0 * ep
        for k in range(steps):
            u = rng.uniform(-high, high) - 0.5 * high / 3.0 * np.r_[x[:3]]
            coarse.append((t0 + k * system.tau, x.copy(), u, ep))
            for j in range(FINE):
                fine.append((t0 + (k + j / FINE) * system.tau, x.copy(), ep))
                x = plant.step(x, u)
        coarse.append((t0 + steps * system.tau, x.copy(), coarse[-1][2], ep))
        fine.append((coarse[-1][0], x.copy(), ep))
    return write_test_log(tmp_path_factory.mktemp("logs") / "lagging", system, "lagging", FINE, coarse, fine)


def test_transitions_carry_the_input_of_the_period_before(lag_log):
    system = load_system("planar3")
    log = read_log(lag_log, system)
    t, x0, u, _ = transitions([log], system.tau, previous_input=True)
    assert u.shape[1] == 6 and len(t) == FINE * (len(log.t) - 5)  # FINE pairs per period, from its start only
    starts = np.isin(x0.numpy(), log.x).all(axis=1)  # every pair starts where a period starts
    assert starts.all()
    at_tau = (t[:, 0] - system.tau).abs() <= 1e-9
    rows = np.flatnonzero(np.r_[log.episode[1:] == log.episode[:-1], False])  # each period's start
    expected_prev = np.where(
        np.r_[False, log.episode[1:] == log.episode[:-1]][rows][:, None], log.u[np.maximum(rows - 1, 0)], log.u[rows]
    )
    assert np.array_equal(u[at_tau, :3].numpy(), log.u[rows]) and np.array_equal(u[at_tau, 3:].numpy(), expected_prev)


def _grown(surrogate: Surrogate) -> Surrogate:
    """The shipped network grown to take the previous input (new inputs deaf), as fine-tuning starts it."""
    system = WithPreviousInput(load_system("planar3"))
    model = widened(surrogate.model, [64, 64, 64, 64], 0, inputs=system.input_box)
    return Surrogate(model, surrogate.tau, system.state_names, system.input_names, meta={"previous_input": True})


def test_a_network_grown_to_take_the_previous_input_starts_as_it_was():
    base = load_surrogate(system="planar3")
    grown = _grown(base)
    rng = np.random.default_rng(1)
    x, u, p = (torch.from_numpy(rng.uniform(-1, 1, (32, n))) for n in (6, 3, 3))
    with torch.no_grad():
        assert torch.allclose(grown.step(x, torch.cat((u, 8 * p), -1)), base.step(x, u), atol=1e-12, rtol=0)
    y, a, b = grown.numpy_flow().step_with_jacobian(x.numpy(), np.concatenate((u, p), -1))
    y0, a0, b0 = base.numpy_flow().step_with_jacobian(x.numpy(), u.numpy())
    assert np.allclose(y, y0, atol=1e-12) and np.allclose(a, a0, atol=1e-10) and np.allclose(b[..., :3], b0)
    assert np.abs(b[..., 3:]).max() < 1e-12  # deaf to the previous input until training turns it on


def test_the_flow_on_states_that_carry_the_previous_input():
    grown = _grown(load_surrogate(system="planar3"))
    with torch.no_grad():  # the new inputs heard: a network that uses u_prev
        first = grown.model.net.layers[0].weight
        first[:, 10:13] = 0.3 * torch.randn(first.shape[0], 3, generator=torch.Generator().manual_seed(0))
    flow = PreviousInputFlow(grown)
    assert (flow.nx, flow.nu, flow.nq) == (9, 3, 3) and flow.state_names[6:] == ("u_joint1_prev", "u_joint2_prev",
                                                                                  "u_joint3_prev")  # fmt: skip
    rng = np.random.default_rng(2)
    s, u = rng.uniform(-1, 1, (4, 9)), rng.uniform(-3, 3, (4, 3))
    fast = flow.numpy_flow()
    y, a, b = fast.step_with_jacobian(s, u)
    assert np.array_equal(y[:, 6:], u) and np.array_equal(a[:, 6:], np.zeros((4, 3, 9)))
    assert np.array_equal(b[:, 6:], np.broadcast_to(np.eye(3), (4, 3, 3)))
    eps = 1e-6
    for j in range(9):  # A by central differences, the u_prev columns included
        ds = np.zeros(9)
        ds[j] = eps
        column = (fast.step(s + ds, u) - fast.step(s - ds, u)) / (2 * eps)
        assert np.allclose(a[:, :, j], column, atol=1e-6), j
    assert np.abs(a[:, :6, 6:]).max() > 1e-4  # the network hears u_prev
    with torch.no_grad():
        yt, at, bt = flow.step_with_jacobian(torch.from_numpy(s), torch.from_numpy(u))
    assert np.allclose(yt.numpy(), y, atol=1e-10) and np.allclose(at.numpy(), a, atol=1e-8)
    assert np.allclose(bt.numpy(), b, atol=1e-8)


def _fine_tune(make_cfg, out, log: str, previous: bool, epochs: int) -> Surrogate:
    """The shipped planar3 network fine-tuned on the log for a few epochs (a real Lightning run)."""
    overrides = [*TINY, f"trainer.max_epochs={epochs}", f"data.logs=[{log}]", "module.weight_robot=1e4",
                 "init_from=pinnmpc/checkpoints/planar3.pt", "model.hidden=[64,64,64,64]",
                 f"model.previous_input={previous}"]  # fmt: skip
    train(make_cfg("train", overrides), out)
    return load_surrogate(out / "surrogate.pt")


def test_fine_tuning_with_the_previous_input_records_it_and_hears_it(make_cfg, tmp_path, lag_log):
    net = _fine_tune(make_cfg, tmp_path, lag_log, True, 2)
    assert takes_previous_input(net) and net.input_names[3:] == ("u_joint1_prev", "u_joint2_prev", "u_joint3_prev")
    rng = np.random.default_rng(3)
    x, u = rng.uniform(-0.5, 0.5, (8, 6)), rng.uniform(-2, 2, (8, 6))
    _, _, b = net.numpy_flow().step_with_jacobian(x, u)
    assert np.abs(b[..., 3:]).max() > 1e-4  # training turned the previous input's weights on


@pytest.mark.slow
def test_fine_tuning_with_the_previous_input_learns_the_lag(make_cfg, tmp_path, lag_log):
    # the same tiny fine-tuning with and without the previous input: with it, the network predicts the lagging
    # robot's steps closer
    system = load_system("planar3")
    t, x0, both, xt = transitions([read_log(lag_log, system)], system.tau, previous_input=True)
    at_tau = (t[:, 0] - system.tau).abs() < 1e-9
    errors = {}
    for previous in (False, True):
        net = _fine_tune(make_cfg, tmp_path / str(previous), lag_log, previous, 12)
        assert takes_previous_input(net) == previous
        with torch.no_grad():
            pred = net.step(x0[at_tau], both[at_tau] if previous else both[at_tau, :3])
        errors[previous] = float((pred - xt[at_tau])[:, :3].square().mean().sqrt())
    assert errors[True] < 0.8 * errors[False], errors  # 0.63 when written


def test_previous_input_needs_logs(make_cfg, tmp_path):
    with pytest.raises(Exception, match=r"model.previous_input=true with data.logs=\[\]"):
        train(make_cfg("train", [*TINY, "model.previous_input=true"]), tmp_path)


def test_the_controller_feeds_the_input_it_applied_last():
    system = load_system("planar3")
    net = _grown(load_surrogate(system="planar3"))
    settings = {"horizon": 5, "Q": [1, 1, 1, 0, 0, 0], "R": [1e-8, 1e-7, 1e-6], "disturbance": {"gain": 0.7}}
    controller = build_nmpc(settings, net, system)
    assert isinstance(controller, PreviousInputNMPC) and controller.describe()["previous_input"]
    assert controller.ocp.nx == 9 and np.array_equal(controller.ocp.weights[np][0][6:], np.zeros((3, 9)))
    t = np.arange(0.0, 4.0, system.tau)
    q = 0.3 * np.sin(np.outer(t, [0.8, 1.1, 1.5]))
    ref = Reference(t, np.hstack([q, np.gradient(q, t, axis=0)]), "sine")
    run = run_loop(controller, _robot(LAG_ONLY), ref, max_steps=25, progress=False)
    assert run.status == "ok" and run.prediction_error.shape[1] == 6 and controller.disturbance.shape == (6,)
    last_state, last_input = controller._last
    assert np.array_equal(last_state[6:], run.u[-2]) and np.array_equal(last_input, run.u[-1])  # s = (x, u applied)
    assert np.abs(controller.ocp.disturbance[6:]).max() == 0.0  # the carried input is never disturbed
    assert np.abs(run.x[:, :3] - ref.x[: len(run.x), :3]).mean() < 0.05


class _PeriodLate:
    """A plant that runs each command over the period after the one it answered, as plant=franka does at
    plant.command_at = tau (the first period: no input)."""

    delay_periods = 1

    def __init__(self, plant: object, nu: int) -> None:
        self.plant, self.running = plant, np.zeros(nu)

    def step(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The state a period on under the command before u; u runs next."""
        x_next = self.plant.step(x, self.running)
        self.running = np.array(u, dtype=np.float64)
        return x_next


def test_with_a_plant_a_period_late_the_monitor_takes_the_input_before_the_one_that_ran():
    """The last period ran the command before the last (a period late), after the one before it: the model monitor's
    prediction takes that one as the previous input, not the command that ran (a settled lag)."""
    system = load_system("planar3")
    net = _grown(load_surrogate(system="planar3"))
    with torch.no_grad():
        net.model.net.layers[0].weight[:, 10:13] = 0.3  # a network that hears the previous input
    settings = {"horizon": 5, "Q": [1, 1, 1, 0, 0, 0], "R": [1e-8, 1e-7, 1e-6], "disturbance": {"gain": 0.7}}
    controller = build_nmpc(settings, net, system)
    t = np.arange(0.0, 2.0, system.tau)
    q = 0.2 * np.sin(np.outer(t, [0.8, 1.1, 1.5]))
    ref = Reference(t, np.hstack([q, np.gradient(q, t, axis=0)]), "sine")
    run = run_loop(controller, _PeriodLate(_robot(LAG_ONLY), 3), ref, max_steps=12, progress=False)
    assert run.status == "ok" and controller.delay_periods == 1
    x, u = run.x, run.u
    missed = controller.prediction_error(x[-2], u[-2], x[-1])
    ran = np.concatenate((x[-1], u[-2]))
    expected = controller.ocp.prediction_error(np.concatenate((x[-2], u[-3])), u[-2], ran)[:6]
    settled = controller.ocp.prediction_error(np.concatenate((x[-2], u[-2])), u[-2], ran)[:6]
    np.testing.assert_allclose(missed, expected, rtol=0, atol=1e-12)
    assert np.abs(expected - settled).max() > 1e-6  # the two differ: the test tells them apart


def test_padded_weights():
    assert padded_weight([1, 2], 2) == [1.0, 2.0, 0.0, 0.0]
    assert padded_weight([[1, 0], [0, 2]], 1) == [[1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 0.0]]
    assert padded_weight(None, 3) is None


def test_the_input_rate_weight_for_a_network_given_the_previous_input(make_cfg):
    # planar3 has no input-rate weight; a network given the previous input gets the arm's own for it
    settings = make_cfg("closed_loop", ["system=planar3"]).controller
    system = load_system("planar3")
    plain = build_nmpc(settings, load_surrogate(system="planar3"), system)
    lagged = build_nmpc(settings, _grown(load_surrogate(system="planar3")), system)
    assert not plain.ocp.has_rate and lagged.ocp.has_rate
    assert np.allclose(np.diag(lagged.ocp.weights[np][2]) ** 2, list(settings.R_rate_previous_input))


def test_a_network_given_the_previous_input_is_not_fine_tuned_as_a_plain_one(make_cfg, lag_log):
    from pinnmpc.training.models import build_model

    overrides = [*TINY, "init_from=pinnmpc/checkpoints/planar3-shop.pt", "model.hidden=[64,64,64,64]",
                 f"data.logs=[{lag_log}]"]  # fmt: skip
    with pytest.raises(ValueError, match="takes 6 inputs, this run's system 3: expected model.previous_input=true"):
        build_model(make_cfg("train", overrides), load_system("planar3"))


def test_the_self_loop_feeds_the_previous_input():
    from pinnmpc.simulation.self_loop import rollout_surrogate, sine_inputs

    base = load_surrogate(system="planar3")
    u = sine_inputs(12, [20.0, -8.0, 2.0])
    deaf = rollout_surrogate(_grown(base), np.zeros(6), u)  # a grown network still deaf to u_prev: as it was
    assert np.allclose(deaf, rollout_surrogate(base, np.zeros(6), u), atol=1e-12, rtol=0)
    hearing = _grown(base)
    with torch.no_grad():
        hearing.model.net.layers[0].weight[:, 10:13] = 0.3
    x = rollout_surrogate(hearing, np.zeros(6), u)
    with torch.no_grad():  # by hand: each step gets the input before it, the first its own
        manual = [torch.zeros(6, dtype=torch.float64)]
        for k in range(len(u)):
            both = torch.from_numpy(np.concatenate((u[k], u[max(k - 1, 0)])))
            manual.append(hearing.step(manual[-1], both))
    assert np.allclose(x, torch.stack(manual).numpy(), atol=1e-12, rtol=0) and not np.allclose(x, deaf, atol=1e-6)


def test_fine_tuning_split_at_a_command_delay_records_it_and_validates_the_split_period(make_cfg, tmp_path, lag_log):
    """model.command_delay: a real fine-tuning on the lagging robot's log records the delay, its best validation is
    the controller's split step on held-out periods (recomputed here to the printed digits), and the controller on
    it carries the previous input."""
    overrides = [*TINY, "trainer.max_epochs=2", f"data.logs=[{lag_log}]", "module.weight_robot=1e4",
                 "init_from=pinnmpc/checkpoints/planar3.pt", "model.hidden=[64,64,64,64]",
                 "model.command_delay=0.01"]  # fmt: skip
    train(make_cfg("train", overrides), tmp_path)
    net = load_surrogate(tmp_path / "surrogate.pt")
    assert net.meta["command_delay"] == 0.01 and not takes_previous_input(net)
    from pinnmpc.surrogate.delayed_command import controller_flow

    flow = controller_flow(net)
    assert takes_previous_input(flow) and flow.input_names[3:] == ("u_joint1_prev", "u_joint2_prev", "u_joint3_prev")
    settings = {"horizon": 3, "Q": [1.0] * 3 + [0.0] * 3, "R": [1e-4] * 3, "R_rate_previous_input": [1e-3] * 3}
    assert isinstance(build_nmpc(settings, net, load_system("planar3")), PreviousInputNMPC)
    best = net.meta["best_val_rmse_position"]
    assert best is not None and 0 < best < 0.05


def test_the_run_starts_with_the_lag_settled_at_its_first_input():
    """The plant and the logs start a run's actuator settled at its first input (here the shop robot's, which the
    network was fine-tuned on): so does the controller's record of the first period, else its first prediction error
    holds a lag from the cold start's zero input that the robot never had, and the offset-free estimate jolts the
    first seconds of the run."""
    system = load_system("planar3")
    controller = build_nmpc(
        {"horizon": 5, "Q": [1, 1, 1, 0, 0, 0], "R": [1e-8, 1e-7, 1e-6], "disturbance": {"gain": 0.7, "notch": False}},
        load_surrogate("pinnmpc/checkpoints/planar3-shop.pt"),
        system,
    )
    t = np.arange(0.0, 1.0, system.tau)
    q = np.tile([0.4, -0.3, 0.2], (len(t), 1))  # held against gravity: the first input is far from zero
    shop = OmegaConf.to_container(system_config("planar3").robots.shop, resolve=True)  # the network's robot
    run = run_loop(controller, _robot(shop), Reference(t, np.hstack([q, 0 * q]), "hold"), max_steps=2, progress=False)
    assert run.status == "ok"
    x, u = run.x, run.u

    def first_error(carried: np.ndarray) -> np.ndarray:
        """The model's miss over the first period with the actuator starting at `carried`."""
        s, ran = np.concatenate((x[0], carried)), np.concatenate((x[1], u[0]))
        return controller.ocp.prediction_error(s, u[0], ran)[:6]

    settled, from_zero = first_error(u[0]), first_error(0 * u[0])
    np.testing.assert_allclose(controller.disturbance, 0.7 * settled, rtol=0, atol=1e-12)  # no bound set here
    np.testing.assert_allclose(run.prediction_error[0], settled, rtol=0, atol=1e-12)  # the monitor's first miss
    assert np.abs(from_zero).max() > 5 * np.abs(settled).max()  # the two differ: the test tells them apart
