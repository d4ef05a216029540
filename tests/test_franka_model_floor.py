"""examples/franka_model_floor.py's model: franky-sim's own FR3 stepped in this process, with franky's command ramp,
as a flow map on (u, u_prev) that the previous-input NMPC runs on (its closed loop on franky-sim: docs/franka.md)."""

from __future__ import annotations

import runpy

import numpy as np
import pytest

from pinnmpc import load_surrogate, load_system
from pinnmpc.controller.build import build_nmpc
from pinnmpc.plant.franka_sim import franky_missing
from pinnmpc.surrogate.flowmap import CompiledRK4
from pinnmpc.surrogate.previous_input import RowValuesFlow
from tests.conftest import ROOT

pytestmark = pytest.mark.skipif(bool(franky_missing()), reason=franky_missing() or "franky present")

FR3_GAINS = np.array([450.0, 450.0, 350.0, 350.0, 100.0, 100.0, 50.0])
FRANKY_ACCELERATION = np.array([15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0])  # franky's FR3 limits, rad/s^2
HOME = np.array([0.0, 0.0, 0.0, -1.5, 0.0, 1.5, 0.0])


@pytest.fixture(scope="module")
def example() -> dict:
    """The example's definitions, without running its main."""
    return runpy.run_path(str(ROOT / "examples" / "franka_model_floor.py"), run_name="example")


def physics(example: dict, ramp_start: float | None) -> object:
    """franky-sim's FR3 at HOME with the served gains."""
    return example["FrankySimPhysics"](HOME, FR3_GAINS, FRANKY_ACCELERATION, ramp_start)


def test_the_servo_holds_the_arm_at_rest(example):
    x0 = np.concatenate([HOME, np.zeros(7)])
    x1 = physics(example, 0.002).period(x0, np.zeros(7), np.zeros(7), 0.05)
    assert np.abs(x1[:7] - HOME).max() < 1e-3, x1[:7] - HOME  # gravity compensated: the arm stays put
    assert np.abs(x1[7:]).max() < 0.05


def test_the_ramp_delays_a_new_command(example):
    x0, command = np.concatenate([HOME, np.zeros(7)]), np.full(7, 0.1)
    ramped = physics(example, 0.002).period(x0, np.zeros(7), command, 0.05)
    stepped = physics(example, None).period(x0, np.zeros(7), command, 0.05)
    settled = physics(example, 0.002).period(x0, command, command, 0.05)  # no change of command: nothing to ramp
    lost = stepped[0] - ramped[0]  # joint 1: 2 ms before the ramp and 0.1 / 15 s along it, about 5e-4 rad at 0.1 rad/s
    assert 2e-4 < lost < 1e-3, lost
    assert np.allclose(settled, physics(example, None).period(x0, command, command, 0.05), atol=1e-12)


def test_a_system_under_the_ramp_is_its_flow_where_the_command_does_not_change(example):
    system = load_system("fr3")
    arm = example["RampedArm"](system, FRANKY_ACCELERATION, 0.002, 0.05, 5e-4)
    x0 = np.tile(np.concatenate([HOME, np.full(7, 0.05)]), (2, 1))
    command = np.array([np.full(7, 0.1), np.full(7, -0.1)])
    settled = arm.rows(x0, np.concatenate([command, command], axis=1), 0.05)
    exact = CompiledRK4(system, 0.05, 5e-4).step(x0, command)
    assert np.abs(settled - exact).max() < 1e-12
    ramped = arm.rows(x0, np.concatenate([command, np.zeros((2, 7))], axis=1), 0.05)
    lost = (exact - ramped)[:, 0] * np.sign(command[:, 0])  # joint 1 behind where the command did not ramp
    assert np.all((lost > 2e-4) & (lost < 1e-3)), lost


def test_its_flow_map_runs_a_previous_input_nmpc(example):
    system = load_system("fr3")
    flow = RowValuesFlow(physics(example, 0.002).rows, load_surrogate(system="fr3"), system)
    x = np.tile(np.concatenate([HOME, np.zeros(7)]), (2, 1))
    u = np.zeros((2, 14))
    y, a, b = flow.step_with_jacobian(x, u)
    assert y.shape == (2, 14) and a.shape == (2, 14, 14) and b.shape == (2, 14, 14)
    assert np.array_equal(flow.step(x[0], u[0]), y[0])
    controller = build_nmpc({"horizon": 3, "Q": [1.0] * 7 + [0.0] * 7, "R": [1e-6] * 7}, flow, system)
    ref = np.tile(np.concatenate([HOME + 0.01, np.zeros(7)]), (3, 1))
    command = controller.make_step(x[0], ref)
    assert command.shape == (7,) and np.all(command > 0)  # every joint is sent towards a reference ahead of it
