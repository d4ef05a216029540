"""examples/shop_model_floor.py's model: the shop robot's own MuJoCo period (its lag starting at the input applied
before) as a flow map on (u, u_prev) (pinnmpc.surrogate.previous_input.RowValuesFlow) with a network's Jacobians,
which the previous-input NMPC runs on (docs/robot.md: what the controller allows once its model is exact)."""

from __future__ import annotations

import runpy

import numpy as np
import pytest
from omegaconf import OmegaConf

pytest.importorskip("mujoco")

from pinnmpc import load_surrogate, load_system  # noqa: E402 (after the skip)
from pinnmpc.controller.build import build_nmpc  # noqa: E402
from pinnmpc.controller.previous_input import PreviousInputNMPC  # noqa: E402
from pinnmpc.plant.mujoco_robot import make_mujoco_plant  # noqa: E402
from pinnmpc.references import Reference  # noqa: E402
from pinnmpc.simulation.loop import run_loop  # noqa: E402
from pinnmpc.surrogate.previous_input import RowValuesFlow  # noqa: E402
from pinnmpc.systems import system_config  # noqa: E402
from tests.conftest import ROOT  # noqa: E402


def test_the_controller_on_the_robots_own_dynamics_predicts_the_robot():
    example = runpy.run_path(str(ROOT / "examples" / "shop_model_floor.py"), run_name="example")
    system = load_system("planar3")
    robots = OmegaConf.to_container(system_config("planar3").robots, resolve=True)
    robot, model = (make_mujoco_plant(system, system.tau, robots, "shop") for _ in range(2))
    network = load_surrogate("pinnmpc/checkpoints/planar3-shop.pt")
    flow = RowValuesFlow(example["robot_rows"](model), network, system)
    settings = {"horizon": 5, "Q": [1, 1, 1, 0, 0, 0], "R": [1e-8, 1e-7, 1e-6], "disturbance": {"gain": 0.7}}
    controller = build_nmpc(settings, flow, system)
    assert isinstance(controller, PreviousInputNMPC)
    t = np.arange(0.0, 2.0, system.tau)
    q = 0.3 * np.sin(np.outer(t, [0.8, 1.1, 1.5]))
    ref = Reference(t, np.hstack([q, np.gradient(q, t, axis=0)]), "sine")
    run = run_loop(controller, robot, ref, max_steps=12, progress=False)
    assert run.status == "ok"
    own = np.abs(run.prediction_error[:, :3]).max()  # the lag's filter 0.7 % from u_prev at each period's start
    x, u = run.x[:-1], run.u
    both = np.concatenate((u, np.concatenate((u[:1], u[:-1]))), axis=1)  # (u, u_prev), the first settled
    networks = np.abs(network.numpy_flow().step(x, both)[:, :3] - run.x[1:, :3]).max()
    assert own < 5e-4 and own < 0.1 * networks, (own, networks)  # the robot's own period, not the network's
