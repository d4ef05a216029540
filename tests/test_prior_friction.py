"""model.prior=frozen_arm_friction: the arm frozen at q0 with its dry friction at the moving velocity, in exponential
Heun sub-steps (pinnmpc.surrogate.prior.friction_substeps), in every form the network is evaluated in."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from pinnmpc import load_system
from pinnmpc.surrogate.casadi_network import prior_function
from pinnmpc.surrogate.prior import FRICTION_STEPS, ArmPrior
from pinnmpc.surrogate.prior_eigen import EigenPriorJacobian
from pinnmpc.training.data import reference_flow
from tests.conftest import central_jacobian, check_substep_flow

TAU = 0.1
KIND = "frozen_arm_friction"


@pytest.fixture(scope="module")
def servo():
    """planar3 as a velocity servo with dry friction at the smoothness a fine-tuning's prior holds (20 s/rad)."""
    base = load_system("planar3")
    smooth = dataclasses.replace(base, actuation="velocity_servo", servo_gain=(20.0, 10.0, 3.0), viscous=(), coulomb=())
    return smooth, dataclasses.replace(smooth, coulomb=(2.0, 1.0, 0.3), coulomb_slope=20.0)


@pytest.fixture(scope="module")
def points(servo):
    """Tracking speeds and commands, an eighth of them small enough for the friction to hold."""
    gen = torch.Generator().manual_seed(5)
    low, high = servo[1].state_box.tensors()
    x0 = low + (high - low) * torch.rand(64, 6, generator=gen, dtype=torch.float64)
    x0[:, 3:] *= 0.2
    u = 3.0 * torch.rand(64, 3, generator=gen, dtype=torch.float64) - 1.5
    u[:8] *= 0.02
    return x0, u


def test_moving_friction_predicts_a_servo_with_dry_friction_closer_than_settled_friction(servo, points) -> None:
    smooth, rough = servo
    x0, u = points
    t = torch.full((64, 1), TAU, dtype=torch.float64)
    true = reference_flow(rough, x0, u, TAU, 1e-4).double()
    settled, moving = (ArmPrior(rough, kind) for kind in ("frozen_arm", KIND))
    assert (settled.steps, moving.steps) == (0, FRICTION_STEPS)
    miss = [(p(t, x0, u)[0] - true).square().mean(0).sqrt() for p in (settled, moving)]
    assert bool((miss[1][:3] < 0.8 * miss[0][:3]).all()), (miss[0], miss[1])  # angles
    assert bool((miss[1][3:] < miss[0][3:]).all()), (miss[0], miss[1])  # velocities
    # without dry friction the kind changes nothing: one exact solve, the same flow
    plain = ArmPrior(smooth, KIND)
    assert plain.steps == 0
    np.testing.assert_array_equal(plain(t, x0, u)[0].numpy(), ArmPrior(smooth)(t, x0, u)[0].numpy())


def test_it_starts_at_x0_and_its_time_derivative_is_exact(servo, points) -> None:
    check_substep_flow(ArmPrior(servo[1], KIND), *points, eps=1e-6, atol=1e-6)


def test_its_compiled_forms_and_jacobians_match_torch_and_finite_differences(servo, points) -> None:
    """The controller's C (AD on small arms, eigendecomposition on large ones) and the export's MX form."""
    prior, (x0, u) = ArmPrior(servo[1], KIND), (a[:6] for a in points)
    t = torch.full((6, 1), TAU, dtype=torch.float64)
    x, jac = prior.with_jacobian(t, x0, u)
    xn, jn = prior.compiled(TAU).with_jacobian(x0.numpy(), u.numpy())
    np.testing.assert_allclose(xn, x.numpy(), atol=1e-12)
    np.testing.assert_allclose(jn.reshape(jac.shape), jac.numpy(), atol=1e-10)
    xe, je = EigenPriorJacobian(prior.arm, TAU, prior.kv.numpy(), prior.steps)(x0.numpy(), u.numpy())
    np.testing.assert_allclose(xe, x.numpy(), atol=1e-12)
    np.testing.assert_allclose(je.reshape(jac.shape), jac.numpy(), atol=1e-9)
    exported = prior_function(prior, TAU)
    for k in range(6):
        np.testing.assert_allclose(np.asarray(exported(x0[k].numpy(), u[k].numpy())).ravel(), xn[k], atol=1e-12)
    numeric = central_jacobian(lambda a, b: prior(t, a, b)[0], x0, u)
    np.testing.assert_allclose(jac.numpy(), numeric.numpy(), atol=1e-6)
    assert float(np.abs(jac[:, :3, 3:6].numpy()).max()) > 1e-3  # v0 moves q(tau) through the lag and friction


def test_an_unknown_kind_is_refused() -> None:
    with pytest.raises(ValueError, match="model.prior='frozen_arm_rk4'; expected null or one of"):
        ArmPrior("planar3", "frozen_arm_rk4")


def test_a_flow_over_another_period_than_the_arms_is_refused(servo) -> None:
    """The sub-steps cut the arm's tau: compiled at another tau the C would not be the torch prior's flow."""
    prior = ArmPrior(servo[1], KIND)
    with pytest.raises(ValueError, match=r"frozen_arm_friction prior's sub-steps cut the arm's period \(0.1 s\)"):
        prior.compiled(0.05)
