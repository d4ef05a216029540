"""model.prior=midpoint_arm: per sub-step the arm held at its predicted mid configuration (M, gravity, drive and the
Coriolis torques taken there), in every form the network is evaluated in."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pinnmpc import load_surrogate, load_system
from pinnmpc.surrogate.prior import MIDPOINT_STEPS, ArmPrior
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
    x0, u = (a[:6] for a in POINTS)
    for part in (0.3 * ARM.tau, 0.7 * ARM.tau):  # a period split in two (pinnmpc.surrogate.delayed_command)
        got = prior.compiled(part).with_jacobian(x0.numpy(), u.numpy())[0]
        want = prior(torch.full((6, 1), part, dtype=torch.float64), x0, u)[0].numpy()
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-10 * max(1.0, np.abs(want).max()))
    with pytest.raises(ValueError, match="a frozen_arm_friction prior's sub-steps cut the arm's period"):
        ArmPrior(ARM, "frozen_arm_friction").compiled(0.3 * ARM.tau)


def test_on_a_long_arm_its_value_is_exact_and_the_held_inertia_jacobian_stands_in() -> None:
    """The Panda (7 joints): the compiled value is the torch prior's; its Jacobian, by AD several times the value's
    cost, is the arm frozen at q0 with its inertia held (prior_stand_in): frozen_arm's exact Jacobian in the v0 and u
    columns, and in all where the arm moves at its steady velocity; near it as close to the exact one as frozen_arm's;
    a stand-in and said to be one."""
    arm = load_system("panda")
    prior, frozen = ArmPrior(arm, KIND), ArmPrior(arm, "frozen_arm")
    x0, u = (a.double() for a in random_pairs(arm, 32, 5))
    steady = torch.cat((x0[:, :7], u), -1)  # v0 = v_ss: the Panda's servo settles at its command (no payload)
    near = torch.cat((x0[:, :7], u + 0.05 * torch.randn(u.shape, generator=torch.Generator().manual_seed(0))), -1)
    compiled, exact_frozen = prior.compiled(arm.tau), frozen.compiled(arm.tau).with_jacobian
    t = torch.full((32, 1), arm.tau, dtype=torch.float64)
    x, _ = prior.with_jacobian(t, x0, u)
    xn, jn = compiled.with_jacobian(x0.numpy(), u.numpy())
    np.testing.assert_allclose(xn, x.numpy(), atol=1e-12)
    jn, jf = jn.reshape(32, 14, 21), exact_frozen(x0.numpy(), u.numpy())[1].reshape(32, 14, 21)
    np.testing.assert_allclose(jn[..., 7:], jf[..., 7:], atol=1e-12)  # v0 and u columns everywhere
    assert np.abs(jn[..., :7] - jf[..., :7]).max() > 1e-3  # q0's differ away from the steady velocity
    at_steady = compiled.jacobian(steady.numpy(), u.numpy())
    np.testing.assert_allclose(at_steady, exact_frozen(steady.numpy(), u.numpy())[1], atol=1e-12)
    _, jac = prior.with_jacobian(t, near, u)
    misses = [
        np.linalg.norm(j.reshape(jac.shape) - jac.numpy(), axis=(1, 2)) / np.linalg.norm(jac.numpy(), axis=(1, 2))
        for j in (compiled.jacobian(near.numpy(), u.numpy()), exact_frozen(near.numpy(), u.numpy())[1])
    ]
    assert float(np.median(misses[0])) < 0.25  # measured 0.16 (a stand-in: not the exact Jacobian, but close)
    assert float(np.median(misses[0])) < 1.1 * float(np.median(misses[1]))  # measured 0.16 both
    shipped = load_surrogate(system="panda")  # the controller is told: its solvers treat their models as inexact
    assert compiled.stand_in_jacobian and shipped.approximate_jacobians
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
