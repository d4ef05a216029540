"""model.prior=frozen_arm: the arm held at q0 solved exactly, the network learning the rest
(pinnmpc.surrogate.prior)."""

from __future__ import annotations

import dataclasses

import casadi as ca
import numpy as np
import pytest
import torch

from pinnmpc import load_surrogate, load_system
from pinnmpc.surrogate import Surrogate
from pinnmpc.surrogate.network import PINN
from pinnmpc.surrogate.prior import EIGEN_FROM_JOINTS, MEMO_SIZE, ArmPrior
from pinnmpc.surrogate.prior_eigen import EigenPriorJacobian, divided_differences
from pinnmpc.training.capacity import one_step_data, run_capacity
from pinnmpc.training.data import CollocationDataModule, reference_flow
from pinnmpc.training.module import PINNModule
from pinnmpc.training.run import train
from pinnmpc.util.checks import SettingError
from tests.conftest import TINY_TRAIN, central_jacobian

TAU = 0.1


@pytest.fixture(scope="module")
def prior() -> ArmPrior:
    return ArmPrior("planar3")


@pytest.fixture(scope="module")
def points() -> tuple[torch.Tensor, torch.Tensor]:
    arm = load_system("planar3")
    gen = torch.Generator().manual_seed(3)
    low, high = arm.state_box.tensors()
    ulow, uhigh = arm.input_box.tensors()
    x0 = low + (high - low) * torch.rand(6, 6, generator=gen, dtype=torch.float64)
    return x0, ulow + (uhigh - ulow) * torch.rand(6, 3, generator=gen, dtype=torch.float64)


def test_the_prior_is_the_flow_of_the_arm_frozen_at_its_start(prior, points) -> None:
    x0, u = points
    arm = prior.arm
    m, c0 = arm.frozen_terms(x0[:, :3], u)  # M(q0) dv/dt = c0 - kv v, integrated by fine RK4 independently
    kv = torch.tensor(arm.viscous, dtype=torch.float64)

    def f(x: torch.Tensor) -> torch.Tensor:
        acc = torch.linalg.solve(m, (c0 - kv * x[:, 3:]).unsqueeze(-1)).squeeze(-1)
        return torch.cat((x[:, 3:], acc), -1)

    x, h = x0.clone(), TAU / 2000
    for _ in range(2000):
        k1 = f(x)
        k2 = f(x + h / 2 * k1)
        k3 = f(x + h / 2 * k2)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + f(x + h * k3))
    t = torch.full((6, 1), TAU, dtype=torch.float64)
    xp, dxp = prior(t, x0, u)
    np.testing.assert_allclose(xp.numpy(), x.numpy(), atol=1e-9)
    np.testing.assert_allclose(dxp.numpy(), f(xp).numpy(), atol=1e-9)  # its time derivative is the frozen rhs
    np.testing.assert_allclose(prior(0 * t, x0, u)[0].numpy(), x0.numpy(), atol=1e-14)  # it starts at x0
    # the true flow differs from it (Coriolis, Coulomb, configuration change): the network's part
    true = one_step_data(arm, TAU, 64, 5e-4, 2)
    miss = (prior(torch.full((64, 1), TAU, dtype=torch.float64), *true[:2])[0] - true[2]).abs().max()
    assert 1e-3 < float(miss) < 0.5 * float((true[2] - true[0]).abs().max())


def test_a_servos_dry_friction_enters_the_prior_where_the_servo_settles() -> None:
    """A velocity servo with dry friction: the frozen drive is K v with v where K (u - v) = C tanh(s v) (sticking
    near rest, never against the command), and that prior predicts the servo's true step (fine RK4 of its rhs)
    closer than the same prior without friction; without friction the drive is K u, as before."""
    base = load_system("planar3")
    servo = dataclasses.replace(base, actuation="velocity_servo", servo_gain=(20.0, 10.0, 3.0), viscous=(), coulomb=())
    rough = dataclasses.replace(servo, coulomb=(2.0, 1.0, 0.3))
    gen = torch.Generator().manual_seed(5)
    low, high = base.state_box.tensors()
    x0 = low + (high - low) * torch.rand(64, 6, generator=gen, dtype=torch.float64)
    x0[:, 3:] *= 0.2  # joint speeds of a tracking arm
    u = 3.0 * torch.rand(64, 3, generator=gen, dtype=torch.float64) - 1.5
    u[:8] *= 0.02  # small commands, which the friction holds
    gain = torch.tensor(servo.servo_gain, dtype=torch.float64)
    c_smooth, c_rough = servo.frozen_terms(x0[:, :3], u)[1], rough.frozen_terms(x0[:, :3], u)[1]
    np.testing.assert_allclose(c_smooth.numpy(), (gain * u).numpy())
    settled = c_rough / gain
    held = torch.tensor(rough.coulomb, dtype=torch.float64) * torch.tanh(rough.coulomb_slope * settled)
    np.testing.assert_allclose((gain * (u - settled)).numpy(), held.numpy(), atol=1e-12)  # the friction balanced
    assert bool((settled * u >= 0).all()) and bool((settled.abs() <= u.abs()).all())
    assert float((settled[:8].abs() / u[:8].abs()).max()) < 0.3  # near rest it sticks
    true = reference_flow(rough, x0, u, TAU, 1e-4).double()
    t = torch.full((64, 1), TAU, dtype=torch.float64)
    miss = [(ArmPrior(arm)(t, x0, u)[0] - true)[:, 3:].square().mean().sqrt() for arm in (rough, servo)]
    assert float(miss[0]) < 0.7 * float(miss[1])


def test_a_servos_joint_damping_enters_the_prior_with_its_gain() -> None:
    """A velocity servo with joint damping D and dry friction: the frozen model's gain is K + D and its drive settles
    where K (u - v) - D v = C tanh(s v); that prior predicts the damped servo's true step closer than the one that
    leaves the damping out."""
    base = load_system("planar3")
    servo = dataclasses.replace(base, actuation="velocity_servo", servo_gain=(20.0, 10.0, 3.0), viscous=(),
                                coulomb=(2.0, 1.0, 0.3))  # fmt: skip
    damped = dataclasses.replace(servo, viscous=(4.0, 2.0, 1.0))
    gen = torch.Generator().manual_seed(6)
    low, high = base.state_box.tensors()
    x0 = low + (high - low) * torch.rand(64, 6, generator=gen, dtype=torch.float64)
    x0[:, 3:] *= 0.2
    u = 3.0 * torch.rand(64, 3, generator=gen, dtype=torch.float64) - 1.5
    gain, damping = (torch.tensor(v, dtype=torch.float64) for v in (damped.servo_gain, damped.viscous))
    np.testing.assert_allclose(damped.linear_gain, (gain + damping).numpy())
    settled = damped.frozen_terms(x0[:, :3], u)[1] / (gain + damping)
    held = torch.tensor(damped.coulomb, dtype=torch.float64) * torch.tanh(damped.coulomb_slope * settled)
    np.testing.assert_allclose((gain * (u - settled) - damping * settled).numpy(), held.numpy(), atol=1e-12)
    true = reference_flow(damped, x0, u, TAU, 1e-4).double()
    t = torch.full((64, 1), TAU, dtype=torch.float64)
    miss = [(ArmPrior(arm)(t, x0, u)[0] - true)[:, 3:].square().mean().sqrt() for arm in (damped, servo)]
    assert float(miss[0]) < 0.5 * float(miss[1]), miss


def test_the_memo_follows_in_place_changes_of_its_inputs(prior, points) -> None:
    x0, u = (a.clone() for a in points)
    t = torch.full((6, 1), TAU, dtype=torch.float64)
    first = prior(t, x0, u)[0]
    assert prior(t, x0, u)[0] is first  # the same tensors: computed once
    x0[:, 3] += 0.5  # in place: a new version of the same storage
    moved = prior(t, x0, u)[0]
    assert not torch.allclose(moved, first)
    np.testing.assert_allclose(moved.numpy(), prior(t, x0.clone(), u.clone())[0].numpy(), rtol=1e-12)


def test_the_compiled_prior_and_its_jacobian_match_torch_and_finite_differences(prior, points) -> None:
    x0, u = points
    fast = prior.compiled(TAU)
    xn, jn = fast.with_jacobian(x0.numpy(), u.numpy())
    np.testing.assert_allclose(fast.value(x0.numpy(), u.numpy())[0], xn, atol=1e-14)
    t = torch.full((6, 1), TAU, dtype=torch.float64)
    x, jac = prior.with_jacobian(t, x0, u)
    np.testing.assert_allclose(xn, x.numpy(), atol=1e-12)
    np.testing.assert_allclose(prior(t, x0.clone(), u.clone())[0].numpy(), x.numpy(), atol=1e-12)  # M in C, no graph
    np.testing.assert_allclose(jn.reshape(jac.shape), jac.numpy(), atol=1e-11)
    numeric = central_jacobian(lambda a, b: prior(t, a, b)[0], x0, u)
    np.testing.assert_allclose(jac.numpy(), numeric.numpy(), atol=1e-7)


def test_the_eigen_jacobian_agrees_with_ad_through_the_series(prior, points) -> None:
    """Two exact derivations (Daleckii-Krein on the eigendecomposition, CasADi AD through Taylor and squarings)."""
    x0, u = (a.numpy() for a in points)
    eigen = EigenPriorJacobian(prior.arm, TAU, prior.kv.numpy())
    x, jac = eigen(x0, u)
    xa, ja = prior.compiled(TAU).with_jacobian(x0, u)
    np.testing.assert_allclose(x, xa, atol=1e-12)
    np.testing.assert_allclose(jac.reshape(6, 6, 9), ja.reshape(6, 6, 9), atol=1e-10)
    assert np.abs(ja.reshape(6, 6, 9)[:, :3, :3] - np.eye(3)).max() > 1e-2  # the q0 columns carry M(q0)'s change


def test_a_seven_joint_arm_takes_the_eigen_path_and_it_matches_finite_differences() -> None:
    panda = ArmPrior("panda")
    arm, tau, n = panda.arm, panda.arm.tau, panda.nq
    fast = panda.compiled(tau)
    assert n >= EIGEN_FROM_JOINTS and isinstance(fast.with_jacobian, EigenPriorJacobian)
    gen = torch.Generator().manual_seed(4)
    (low, high), (ulow, uhigh) = arm.state_box.tensors(), arm.input_box.tensors()
    x0 = low + (high - low) * torch.rand(3, 2 * n, generator=gen, dtype=torch.float64)
    u = ulow + (uhigh - ulow) * torch.rand(3, n, generator=gen, dtype=torch.float64)
    xn, jn = fast.with_jacobian(x0.numpy(), u.numpy())
    np.testing.assert_allclose(fast.value(x0.numpy(), u.numpy())[0], xn, atol=1e-12)
    t = torch.full((3, 1), tau, dtype=torch.float64)
    numeric = central_jacobian(lambda a, b: panda(t, a, b)[0], x0, u)
    np.testing.assert_allclose(jn.reshape(3, 2 * n, 3 * n), numeric.numpy(), atol=1e-6)


def test_divided_differences_at_a_double_eigenvalue_are_the_derivative() -> None:
    lam = [ca.SX.sym(f"l{k}") for k in range(3)]
    f = [ca.exp(-a) for a in lam]
    fun = ca.Function("dd", lam, [divided_differences(lam, f, [-v for v in f])])
    at = [2.0, 2.0 * (1 + 1e-9), 5.0]
    out = np.array(fun(*at))
    assert np.isfinite(out).all()
    np.testing.assert_allclose(np.diag(out), -np.exp(-np.array(at)), rtol=1e-12)
    np.testing.assert_allclose(out[0, 1], -np.exp(-2.0), rtol=1e-8)  # f' where the pair (nearly) coincides
    np.testing.assert_allclose(out[0, 2], (np.exp(-2.0) - np.exp(-5.0)) / (2.0 - 5.0), rtol=1e-12)


def test_a_network_with_the_prior_is_the_same_in_torch_and_numpy_and_survives_a_save(prior, points, tmp_path) -> None:
    x0, u = points
    arm = prior.arm
    torch.manual_seed(0)
    net = PINN(
        *arm.state_box.tensors(), *arm.input_box.tensors(), t_max=0.125, hidden=[16, 16], activation="silu",
        ic="gated", time_basis=[0.004, 0.05], periodic=[0, 1, 2], prior={"kind": "frozen_arm", "system": "planar3"},
    ).double()  # fmt: skip
    s = Surrogate(net, TAU, arm.state_names, arm.input_names, {})
    x, a, b = s.step_with_jacobian(x0, u)
    xn, an, bn = s.numpy_flow().step_with_jacobian(x0.numpy(), u.numpy())
    np.testing.assert_allclose(xn, x.numpy(), atol=1e-12)
    np.testing.assert_allclose(an, a.numpy(), atol=1e-11)
    np.testing.assert_allclose(bn, b.numpy(), atol=1e-11)
    np.testing.assert_allclose(s.numpy_flow().step(x0.numpy(), u.numpy()), xn, atol=1e-14)
    with torch.no_grad():  # the network's part starts at zero: x(0) = x0 exactly
        np.testing.assert_allclose(net(torch.zeros(6, 1, dtype=torch.float64), x0, u).numpy(), x0.numpy(), atol=1e-14)
    back = load_surrogate(s.save(tmp_path / "prior.pt"))
    assert back.model.config["prior"] == {"kind": "frozen_arm", "system": "planar3"}
    np.testing.assert_allclose(back.step(x0, u).numpy(), x.numpy(), atol=1e-12)


def test_a_direct_fit_with_the_prior_starts_far_closer(make_cfg, tmp_path) -> None:
    tiny = ["points=256", "val_points=64", "max_steps=1", "model.hidden=[16,16]", "model.auto_scale.samples=64"]
    plain = ["system=planar3", "plots=false", "system.network.prior=null", *tiny]
    plain = run_capacity(make_cfg("capacity", plain), tmp_path / "a")
    with_prior = ["system=planar3", "plots=false", "system.network.prior=frozen_arm", *tiny]
    m = run_capacity(make_cfg("capacity", with_prior), tmp_path / "b")
    # untrained networks: the prior alone is already several times closer in every state than x0 plus a random net
    assert np.all(np.array(m["initial_val_rmse"]) < 0.25 * np.array(plain["initial_val_rmse"]))


def test_training_with_the_prior_lowers_the_loss_and_exports_it(make_cfg, tmp_path) -> None:
    fine = "model.auto_scale.h=1e-3"  # the tiny runs' 1e-2 RK4 step diverges on planar3's stiff flow
    overrides = [*TINY_TRAIN, fine, "trainer.max_epochs=3"]
    summary = train(make_cfg("train", ["system=planar3", "system.network.prior=frozen_arm", *overrides]), tmp_path)
    s = load_surrogate(tmp_path / "surrogate.pt")
    assert s.model.config["prior"]["system"] == "planar3" and summary["epochs"] == 3
    x0, u, x1 = one_step_data(load_system("planar3"), TAU, 64, 5e-4, 7)
    assert float((s.step(x0, u) - x1).abs().max()) < float((x1 - x0).abs().max())
    # resuming it without the prior would load the same weights into another function: refused
    more = [*TINY_TRAIN, fine, "trainer.max_epochs=4", "resume=true"]  # budget left: the prior is what differs
    plain = make_cfg("train", ["system=planar3", "system.network.prior=null", *more])
    said = "trained with model.prior=frozen_arm, this configuration has model.prior=null"
    with pytest.raises(ValueError, match=said):
        train(plain, tmp_path)


def test_the_prior_is_refused_where_it_cannot_work(make_cfg, tmp_path) -> None:
    with pytest.raises(ValueError, match="needs an arm from a URDF.*system='powercube' is PowerCube"):
        ArmPrior("powercube")
    box = dict(state_low=[-1.0] * 6, state_high=[1.0] * 6, input_low=[-1.0] * 3, input_high=[1.0] * 3, t_max=0.1)
    with pytest.raises(ValueError, match="model.prior='euler'; expected null or one of"):
        PINN(**box, prior={"kind": "euler", "system": "planar3"})
    with pytest.raises(ValueError, match="a prior needs a first-order network with an exact initial condition"):
        PINN(**box, ic="soft", prior={"kind": "frozen_arm", "system": "planar3"})
    coarse = ["system=planar3", *TINY_TRAIN, "model.auto_scale.h=1e-2"]
    with pytest.raises(ValueError, match="model.auto_scale.h=0.01: RK4 at this step diverges on planar3's flow"):
        train(make_cfg("train", coarse), tmp_path)
    said = "model.prior=.frozen.: expected one of frozen_arm, frozen_arm_friction, frozen_arm_moving, midpoint_arm or"
    with pytest.raises(SettingError, match=said):
        run_capacity(make_cfg("capacity", ["system=planar3", "system.network.prior=frozen"]), tmp_path / "c")


def test_training_steps_on_the_same_points_compute_the_prior_once(prior) -> None:
    """The float64 points are cast to float32 once per draw, so the prior's memo holds across steps."""
    arm = prior.arm
    net = PINN(
        *arm.state_box.tensors(), *arm.input_box.tensors(), t_max=0.125, hidden=[16, 16], activation="silu",
        ic="gated", time_basis=[0.004, 0.05], periodic=[0, 1, 2], prior={"kind": "frozen_arm", "system": "planar3"},
    )  # fmt: skip
    dm = CollocationDataModule(arm, TAU, 0.125, n_collocation=128, n_data=8, n_val=16, val_h=1e-3, n_anchor=32)
    dm.setup()
    module = PINNModule(arm, net, tau=TAU)

    def sets() -> set:
        """The memo's entries (key, result) for the collocation and anchor points (the data loss's t = 0 is built
        anew each call): a recomputed set has a new result."""
        return {(k, id(v[1])) for k, v in net.prior._memo.items() if k[0][2][0] >= 32}

    first = float(module.losses(dm.batch)["total"].detach())
    before = sets()
    assert len(before) == 2
    for _ in range(2 * MEMO_SIZE):  # more steps than the memo holds sets: the data loss's new t = 0 each time
        assert float(module.losses(dm.batch)["total"].detach()) == first
    assert sets() == before  # the same copies, kept as the most recently used: nothing recomputed
    dm.batch["x0"].mul_(1.0)  # changed in place (the same values): a new copy, a new prior for those points
    module.losses(dm.batch)
    assert len(sets() - before) == 1
