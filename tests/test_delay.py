"""A plant that holds each input a period late (a robot with plant.command_at = tau): the closed loop hands the delay
to the controller, which plans from its model's prediction of the state the input will meet."""

from __future__ import annotations

import numpy as np
import pytest

from pinnmpc.plant.build import make_plant
from pinnmpc.robot_data.collect import applied
from pinnmpc.simulation.loop import run_loop
from pinnmpc.simulation.setup import build_controller, system_reference
from pinnmpc.systems.registry import build_system

SETTLED = 15  # samples after the start: the first command of a late plant meets an arm that has not moved yet


class LatePlant:
    """The real scipy plant with each input applied one period after it was given, as a robot whose commands go out
    as the next period begins; `declared`: whether it says so (delay_periods)."""

    def __init__(self, plant, nu: int, declared: bool = True) -> None:
        self.plant, self.running, self.delay_periods = plant, np.zeros(nu), int(declared)

    def step(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        x = self.plant.step(x, self.running)
        self.running = np.asarray(u, dtype=np.float64).copy()
        return x


def _tracking(make_cfg, controller: str, late: bool | None) -> float:
    """Worst-joint MAE after the start of 60 samples on planar3's default reference; late None: an on-time plant."""
    cfg = make_cfg("closed_loop", ["system=planar3", f"controller={controller}", "progress=false"])
    system = build_system(cfg.system)
    ctrl, domain, tau = build_controller(cfg, system)
    ref = system_reference(cfg, system, tau)
    plant = make_plant(system, cfg.plant, tau)
    if late is not None:
        plant = LatePlant(plant, system.nq, declared=late)
    run = run_loop(ctrl, plant, ref, max_steps=60, domain=domain, progress=False)
    assert run.status == "ok", run.status
    n, q = len(run.x), slice(0, system.nq)
    return float(np.abs(run.x[SETTLED:, q] - ref.x[SETTLED:n, q]).mean(axis=0).max())


@pytest.mark.parametrize("controller", ["exact", "casadi"])
def test_with_an_exact_model_a_late_plant_tracks_as_an_on_time_one(make_cfg, controller: str) -> None:
    on_time = _tracking(make_cfg, controller, None)
    compensated = _tracking(make_cfg, controller, True)
    ignored = _tracking(make_cfg, controller, False)
    assert compensated <= 1.05 * on_time, (compensated, on_time)
    assert ignored >= 100 * compensated, (ignored, compensated)  # the same delay, not planned for


def test_the_network_controller_plans_ahead_of_a_late_plant(make_cfg) -> None:
    compensated, ignored = _tracking(make_cfg, "nmpc", True), _tracking(make_cfg, "nmpc", False)
    assert ignored >= 20 * compensated, (ignored, compensated)


def test_a_late_plants_logs_hold_the_input_that_drove_each_period() -> None:
    commands = np.arange(6.0).reshape(3, 2)
    held = applied(commands, LatePlant(None, 2))
    np.testing.assert_array_equal(held, [[0, 0], [0, 1], [2, 3]])
    np.testing.assert_array_equal(applied(commands, object()), commands)  # an on-time plant: the commands


class ClippingPlant(LatePlant):
    """A late plant whose safety layer clips every command to +-limit and says what it sent (as plant=franka)."""

    def __init__(self, plant, nu: int, limit: float) -> None:
        super().__init__(plant, nu)
        self.limit, self.last_command = limit, None

    def step(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        self.last_command = np.clip(np.asarray(u, dtype=np.float64), -self.limit, self.limit)
        return super().step(x, self.last_command)


def test_the_loop_logs_and_plans_with_the_input_the_plant_sent(make_cfg) -> None:
    cfg = make_cfg("closed_loop", ["system=planar3", "progress=false"])
    system = build_system(cfg.system)
    ctrl, domain, tau = build_controller(cfg, system)
    ref = system_reference(cfg, system, tau)
    free = run_loop(ctrl, LatePlant(make_plant(system, cfg.plant, tau), system.nq), ref, max_steps=30, progress=False)
    limit = 0.5 * float(np.abs(free.u).max())
    plant = ClippingPlant(make_plant(system, cfg.plant, tau), system.nq, limit)
    run = run_loop(ctrl, plant, ref, max_steps=30, domain=domain, progress=False)
    assert run.status == "ok" and np.abs(run.u).max() <= limit  # the inputs logged are those sent
    np.testing.assert_array_equal(ctrl.u_prev.numpy(), run.u[-1])  # the next plan starts from the one running
    assert ctrl.describe()["disturbance_notch"]  # notch=null: on while the plant runs late (docs/franka.md)
    run_loop(ctrl, make_plant(system, cfg.plant, tau), ref, max_steps=3, progress=False)
    assert not ctrl.describe()["disturbance_notch"]  # and off again on time (planar3.pt: not fine-tuned on logs)
