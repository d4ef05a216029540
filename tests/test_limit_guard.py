"""The joint-limit guard (issue 63, opt-in): on the shipped panda network, an input that would carry joint 4 past its
upper limit within a period is moved to the nearest input that keeps the margin; inputs well inside pass unchanged."""

from __future__ import annotations

import numpy as np
import pytest

from pinnmpc.controller.build import build_nmpc
from pinnmpc.controller.limit_guard import LimitGuard
from pinnmpc.controller.ocp import JointLimits
from pinnmpc.surrogate import load_surrogate
from pinnmpc.systems import load_system

GUARD = {"margin": 0.002, "lookahead": 0.0, "miss_gain": 0.0, "iterations": 3}


@pytest.fixture(scope="module")
def nmpc() -> object:
    """The panda NMPC with the guard on (short horizon: only its one-step model is used here)."""
    panda = load_system("panda")
    limits = JointLimits(panda.joint_limits.low, panda.joint_limits.high, 1e5, 0.01)
    cfg = {"horizon": 2, "Q": [1.0] * 7 + [0.0] * 7, "R": [1e-6] * 7, "joint_limits": limits, "limit_guard": GUARD}
    return build_nmpc(cfg, load_surrogate(system="panda"))


def test_guard_moves_an_input_that_would_cross_onto_the_margin(nmpc: object) -> None:
    guard, high = nmpc.guard, nmpc.ocp.joint_limits.high[3]
    x = np.zeros(14)
    x[:7] = [0.0, 0.0, 0.0, -0.08, 0.0, 1.5, 0.0]
    x[10] = 1.0  # joint 4 moving up onto its limit (-0.0698 rad)
    u = np.zeros(7)
    assert nmpc._step_jacobian(x, u)[0][3] > high  # unguarded, the model carries it past
    guard.reset()
    out = guard.filter(x, u, nmpc._low, nmpc._high)
    assert nmpc._step_jacobian(x, out)[0][3] <= high - GUARD["margin"] + 1e-6
    assert guard.active == 1 and np.all(out >= nmpc._low) and np.all(out <= nmpc._high)


def test_guard_leaves_inputs_well_inside_alone(nmpc: object) -> None:
    x = np.zeros(14)
    x[:7] = [0.0, 0.0, 0.0, -1.5, 0.0, 1.5, 0.0]
    u = np.full(7, 0.3)
    nmpc.guard.reset()
    np.testing.assert_array_equal(nmpc.guard.filter(x, u, nmpc._low, nmpc._high), u)
    assert nmpc.guard.active == 0


def test_guard_settings_are_checked() -> None:
    limits = JointLimits((-1.0,), (1.0,), 1e5, 0.01)
    with pytest.raises(ValueError, match="unknown keys"):
        LimitGuard.from_config({"margn": 0.1}, limits, lambda x, u: (x, np.zeros((2, 1))), 0.05)
    with pytest.raises(ValueError, match="margin"):
        LimitGuard.from_config({"margin": -1.0}, limits, lambda x, u: (x, np.zeros((2, 1))), 0.05)
    assert LimitGuard.from_config(None, limits, lambda x, u: (x, np.zeros((2, 1))), 0.05) is None
