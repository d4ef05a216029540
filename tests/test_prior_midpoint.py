"""model.prior=midpoint_arm: per sub-step the arm held at its predicted mid configuration (M, gravity, drive and the
Coriolis torques taken there), in every form the network is evaluated in."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pinnmpc import load_surrogate, load_system
from pinnmpc.surrogate.prior import MIDPOINT_JACOBIAN, MIDPOINT_STEPS, ArmPrior
from pinnmpc.surrogate.substeps import midpoint_substeps, relaxation
from pinnmpc.systems.sampling import random_pairs
from tests.conftest import check_compiled_prior, check_substep_flow, prior_misses

KIND = "midpoint_arm"


ARM = load_system("planar3")  # torque-driven, viscous and dry friction: its links swing far within a period
POINTS = tuple(a.double() for a in random_pairs(ARM, 64, 3))  # fresh states and torques over the training box


def test_taking_the_arm_at_its_mid_configuration_brings_the_prior_much_closer() -> None:
    mid = ArmPrior(ARM, KIND)
    assert (mid.steps, mid.coriolis, mid.midpoint) == (MIDPOINT_STEPS, True, True)
    miss = prior_misses(ARM, ("frozen_arm_moving", KIND), *POINTS)
    # measured: 3.6-11x closer per state (the angles least)
    assert bool((miss[1] < miss[0] / 3).all()), (miss[0], miss[1])


def test_it_starts_at_x0_and_its_time_derivative_is_exact() -> None:
    check_substep_flow(ArmPrior(ARM, KIND), *POINTS, eps=1e-7, atol=1e-5)


def test_its_compiled_and_exported_forms_and_jacobian_match_torch_and_finite_differences() -> None:
    prior = ArmPrior(ARM, KIND)
    check_compiled_prior(prior, *(a[:6] for a in POINTS))
    with pytest.raises(ValueError, match="a midpoint_arm prior's sub-steps cut the arm's period"):
        prior.compiled(2 * ARM.tau)


def test_on_a_long_arm_its_value_is_exact_and_the_frozen_arms_jacobian_stands_in() -> None:
    """The Panda (7 joints): the compiled value is the torch prior's; its Jacobian, by AD several times the value's
    cost, is the arm held at q0's (MIDPOINT_JACOBIAN, exact by eigendecomposition), a stand-in and said to be one."""
    arm = load_system("panda")
    prior, held = ArmPrior(arm, KIND), ArmPrior(arm, MIDPOINT_JACOBIAN)
    x0, u = random_pairs(arm, 16, 5)
    x0, u = x0.double(), u.double()
    x, jac = prior.with_jacobian(torch.full((16, 1), arm.tau, dtype=torch.float64), x0, u)
    xn, jn = prior.compiled(arm.tau).with_jacobian(x0.numpy(), u.numpy())
    np.testing.assert_allclose(xn, x.numpy(), atol=1e-12)
    np.testing.assert_array_equal(jn, held.compiled(arm.tau).with_jacobian(x0.numpy(), u.numpy())[1])
    miss = np.linalg.norm(jn.reshape(jac.shape) - jac.numpy(), axis=(1, 2)) / np.linalg.norm(jac.numpy(), axis=(1, 2))
    assert 0.01 < float(np.median(miss)) < 0.25  # measured 0.12 (a stand-in: not the exact Jacobian, but close)
    shipped = load_surrogate(system="panda")  # the controller is told: its solvers treat their models as inexact
    assert prior.compiled(arm.tau).stand_in_jacobian and shipped.approximate_jacobians
    assert shipped.numpy_flow().approximate_jacobians
    assert not ArmPrior(ARM, KIND).compiled(ARM.tau).stand_in_jacobian  # planar3: its own, by AD


def test_each_sub_step_takes_one_mass_matrix_and_one_coriolis_torque() -> None:
    """The predictor holds the arm without its moving torques, and the end velocity is predicted with the torques the
    sub-step before held: per period steps + 1 of each (the first at x0 itself), what the value costs most."""
    prior = ArmPrior(ARM, KIND)
    calls = {"torque": 0, "terms": 0}
    kv, h = prior.kv, ARM.tau / prior.steps
    x0, u = POINTS

    def terms(q: torch.Tensor) -> tuple:
        calls["terms"] += 1
        m, a, vss = prior._terms(q, u)
        return vss, relaxation(m, torch.linalg.matrix_exp(-a * h), kv)

    def moving(q: torch.Tensor) -> object:
        held = prior.moving_torque(q)

        def torque(w: torch.Tensor) -> torch.Tensor:
            calls["torque"] += 1
            return held(w)

        return torque

    with torch.no_grad():
        end = midpoint_substeps((x0[:, : ARM.nq], x0[:, ARM.nq :]), terms, moving, kv, h, prior.steps)
        x = prior(torch.full((x0.shape[0], 1), ARM.tau, dtype=torch.float64), x0, u)[0]
    assert calls == {"torque": MIDPOINT_STEPS + 1, "terms": MIDPOINT_STEPS + 1}, calls
    torch.testing.assert_close(torch.cat(end, -1), x, rtol=0, atol=1e-12)  # the formula the controller's C takes
