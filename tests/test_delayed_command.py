"""A network split at a command delay (pinnmpc.surrogate.delayed_command): the period's first part under the previous
input, the rest under the new one, its Jacobian by the chain rule, the numpy path as the torch one, a controller that
runs on it; the training settings that make such a network."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pinnmpc import load_surrogate
from pinnmpc.controller.build import build_nmpc
from pinnmpc.surrogate.delayed_command import DelayedCommandFlow, controller_flow
from pinnmpc.systems import load_system


def split(name: str, delay: float) -> tuple[object, DelayedCommandFlow]:
    """The shipped network of `name` and its flow split at delay s."""
    net = load_surrogate(system=name)
    net.meta = {**net.meta, "command_delay": delay}
    return net, controller_flow(net)


@pytest.mark.parametrize("name", ["planar3", "fr3"])
def test_a_split_period_is_the_network_twice_under_each_input(name: str) -> None:
    """x(tau) = G(tau - d, G(d, x0, u_prev), u); with u_prev = u the prior's flow composes (the network's own miss
    aside); the Jacobian is the chain rule's, equal to autograd's of the split map; the numpy path (midpoint_arm's
    prior compiled at t = d and tau - d on the FR3) gives the torch path's values."""
    net, flow = split(name, 0.004)
    system = load_system(name)
    nx, nu = len(system.state_names), len(system.input_names)
    assert flow.meta["previous_input"] and len(flow.input_names) == 2 * nu and flow.tau == pytest.approx(net.tau)
    rng = np.random.default_rng(0)
    x0 = torch.tensor(0.5 * (np.asarray(system.state_box.low) + np.asarray(system.state_box.high)))
    x0 = x0 + 0.05 * torch.tensor(rng.standard_normal(nx))
    u, before = (0.1 * torch.tensor(rng.standard_normal(nu)) for _ in range(2))
    both = torch.cat((u, before))
    expect = net.at(net.tau - 0.004).step(net.at(0.004).step(x0, before), u)
    x1, a, b = flow.step_with_jacobian(x0, both)
    assert torch.allclose(flow.step(x0, both), expect, rtol=0, atol=1e-12) and torch.allclose(x1, expect, atol=1e-12)
    ja, jb = torch.autograd.functional.jacobian(flow.step, (x0, both))
    assert torch.allclose(a, ja, atol=1e-8) and torch.allclose(b, jb, atol=1e-8)
    assert b[:, nu:].abs().max() > 1e-4  # u_prev moves the state: the delay is in the map
    fast = flow.numpy_flow()
    assert fast is not None and fast.array_api == "numpy"
    np.testing.assert_allclose(fast.step(x0.numpy()[None], both.numpy()[None])[0], expect.numpy(), atol=1e-10)
    prior = net.model.prior
    if prior is not None:
        t = lambda s: torch.full((1, 1), s, dtype=torch.float64)  # noqa: E731
        held = prior(t(net.tau - 0.004), prior(t(0.004), x0[None], u[None])[0], u[None])[0]
        assert (held - prior(t(net.tau), x0[None], u[None])[0]).abs().max() < 1e-5


def test_a_controller_on_a_split_network_carries_the_previous_input() -> None:
    """build_nmpc on a network whose meta has a command_delay plans on states (x, u_prev) and answers in the arm's
    inputs; a delay outside (0, tau) is refused in one line."""
    net, _ = split("planar3", 0.01)
    settings = {"horizon": 3, "Q": [1.0, 1.0, 1.0, 0.0, 0.0, 0.0], "R": [1e-4] * 3, "R_rate_previous_input": [1e-3] * 3}
    controller = build_nmpc(settings, net, load_system("planar3"))
    assert controller.describe()["previous_input"]
    ref = np.tile([0.3, -0.2, 0.1, 0.0, 0.0, 0.0], (3, 1))
    u = controller.make_step(np.zeros(6), ref)
    assert np.shape(u) == (3,) and np.isfinite(u).all()
    net.meta["command_delay"] = net.tau
    with pytest.raises(ValueError, match=r"command_delay=0.1 s in the network's meta; expected 0 < delay < its period"):
        controller_flow(net)


def test_command_delay_settings_are_checked_in_one_line(make_cfg) -> None:
    """model.command_delay with previous_input, or at the period, is refused before training."""
    from pinnmpc.training.job_settings import validate_train
    from pinnmpc.util.checks import SettingError

    for overrides in (["model.command_delay=0.004", "model.previous_input=true", "data.logs=[x.npz]"],
                      ["model.command_delay=0.1"]):  # fmt: skip
        cfg = make_cfg("train", ["system=planar3", *overrides])
        with pytest.raises(SettingError, match=r"model.command_delay=0.\d+ with model.previous_input"):
            validate_train(cfg, load_system("planar3"))
