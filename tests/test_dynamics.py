"""The single source of physics: golden vectors, torch/numpy agreement, structure the solvers rely on."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pinnmpc.plant import PlantError, ScipyPlant
from pinnmpc.plant.integrators import euler_step, rk4_step
from pinnmpc.systems import Box, PowerCube, PowerCubeParams, load_system
from pinnmpc.systems.powercube import mass_matrix, mass_residual

rhs = load_system("powercube").rhs  # the nominal PowerCube, as users load it


def test_rhs_matches_golden(golden):
    out = rhs(torch.tensor(golden["x"]), torch.tensor(golden["u"]))
    assert out.dtype == torch.float64
    assert np.abs(out.numpy() - golden["dxdt"]).max() <= 1e-10


def test_plant_matches_golden_step(golden):
    """Plain RK45 is the paper's plant to round-off; by default the steps where joint B's sign(v) friction chatters
    (two of the sixteen) are redone by stick-slip modes (tests/test_stick_slip.py) and land within RK45's tolerance."""
    tau, cases = float(golden["step_tau"]), list(zip(golden["step_x0"], golden["step_u"]))
    plain, plant = ScipyPlant(PowerCube(), tau, chatter_flips=None), ScipyPlant(PowerCube(), tau)
    x1_plain = np.stack([plain.step(x0, u) for x0, u in cases])
    x1 = np.stack([plant.step(x0, u) for x0, u in cases])
    assert np.abs(x1_plain - golden["step_x1"]).max() <= 1e-6
    assert len(plant.step_times) == len(x1) and plant.stick_slip_steps == 2
    redone = np.abs(x1 - x1_plain).max(axis=1) > 0
    assert redone.sum() == 2 and np.abs(x1 - golden["step_x1"]).max() <= 1e-4


def test_numpy_and_torch_share_formulas():
    rng = np.random.default_rng(0)
    x, u = rng.uniform(-2, 2, (50, 4)), rng.uniform(-0.5, 0.5, (50, 2))
    sys = PowerCube()
    assert np.allclose(sys.rhs(x, u), sys.rhs(torch.tensor(x), torch.tensor(u)).numpy(), rtol=0, atol=1e-12)


def test_rhs_batched_and_differentiable():
    x = torch.rand(3, 5, 4, dtype=torch.float64, requires_grad=True)
    u = torch.rand(3, 5, 2, dtype=torch.float64)
    out = rhs(x, u)
    assert out.shape == (3, 5, 4)
    out.sum().backward()
    assert torch.all(torch.isfinite(x.grad))


def test_zero_velocity_uses_sign_zero():
    x = torch.zeros(1, 4, dtype=torch.float64)
    u = torch.zeros(1, 2, dtype=torch.float64)
    assert torch.allclose(rhs(x, u), torch.zeros(1, 4, dtype=torch.float64))


def test_mass_matrix_positive_definite():
    beta = torch.linspace(-np.pi, np.pi, 101, dtype=torch.float64)
    x = torch.stack((torch.zeros_like(beta), beta, torch.zeros_like(beta), torch.zeros_like(beta)), -1)
    m11, m12, m22 = mass_matrix(x)
    assert torch.all(m11 > 0) and torch.all(m11 * m22 - m12**2 > 0)


def test_mass_residual_vanishes_on_true_derivative():
    x = torch.rand(20, 4, dtype=torch.float64) * 2 - 1
    u = torch.rand(20, 2, dtype=torch.float64) - 0.5
    res = mass_residual(x, rhs(x, u), u)
    assert res.abs().max() < 1e-10


def test_mismatch_scales_change_the_plant_only_when_asked():
    x = torch.tensor([[0.3, -0.2, 0.5, -0.4]], dtype=torch.float64)
    u = torch.tensor([[0.1, -0.1]], dtype=torch.float64)
    nominal = PowerCube().rhs(x, u)
    assert torch.equal(PowerCube(PowerCubeParams(friction_scale=1.0)).rhs(x, u), nominal)
    assert not torch.allclose(PowerCube(PowerCubeParams(friction_scale=1.2)).rhs(x, u), nominal)


def test_bad_shapes_are_named():
    with pytest.raises(ValueError, match="expected 4"):
        rhs(torch.zeros(3), torch.zeros(2))
    with pytest.raises(ValueError, match="expected 2"):
        PowerCube().rhs(torch.zeros(4), torch.zeros(3))


def test_box_validation():
    with pytest.raises(ValueError, match="low 1.0 > high 0.0"):
        Box((1.0,), (0.0,))
    box = Box((0.0, 0.0), (1.0, 1.0))
    assert torch.equal(box.excess(torch.tensor([[0.5, 1.5]])), torch.tensor([[0.0, 0.5]]))


def test_fixed_step_integrators_converge_to_plant():
    sys = PowerCube()
    x0 = torch.tensor([[0.5, -0.3, 0.2, 0.4]], dtype=torch.float64)
    u = torch.tensor([[0.2, -0.1]], dtype=torch.float64)
    fine = rk4_step(sys.rhs, x0, u, 0.2, 1e-4)
    coarse = rk4_step(sys.rhs, x0, u, 0.2, 1e-3)
    euler = euler_step(sys.rhs, x0, u, 0.2, 1e-4)
    assert (fine - coarse).abs().max() < 1e-4
    assert (fine - euler).abs().max() < 1e-2
    plant = ScipyPlant(sys, 0.2, rtol=1e-10, atol=1e-12)
    assert np.abs(plant.step(x0[0].numpy(), u[0].numpy()) - fine[0].numpy()).max() < 1e-5


def test_plant_failure_is_an_error():
    plant = ScipyPlant(PowerCube(), 0.2)
    with pytest.raises(PlantError, match="non-finite"):
        plant.step(np.array([np.nan, 0.0, 0.0, 0.0]), np.zeros(2))
    with pytest.raises(ValueError, match="tau must be > 0"):
        ScipyPlant(PowerCube(), 0.0)


def test_physics_parameters_are_validated():
    with pytest.raises(ValueError, match="friction_scale must be a finite number, got nan"):
        PowerCubeParams(friction_scale=float("nan"))
    with pytest.raises(ValueError, match="mass_scale must be a finite number, got '.nan'"):
        PowerCubeParams(mass_scale=".nan")
    with pytest.raises(ValueError, match="mass_scale > 0"):
        PowerCubeParams(mass_scale=0.0)


@pytest.mark.parametrize("name", ["powercube", "planar3"])
def test_mass_scale_is_a_heavier_arm_on_every_system(name: str) -> None:
    # every link's mass and inertia scaled: M, Coriolis and gravity alike, so an arm at rest under no input falls
    # as the nominal one does (the PowerCube once left its gravity moments unscaled: half the acceleration)
    arm = load_system(name)
    x = np.zeros(arm.state_box.dim)
    x[0] = 0.7
    u = np.zeros(arm.input_box.dim)
    nominal, heavy = arm.rhs(x, u), arm.with_mismatch(mass_scale=2.0).rhs(x, u)
    assert np.abs(nominal[arm.state_box.dim // 2 :]).max() > 1.0  # it falls
    np.testing.assert_allclose(heavy, nominal, rtol=1e-12, atol=1e-12)
