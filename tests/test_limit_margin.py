"""Joint limits hold with margin (issue 63): closed loops of the shipped controllers from many perturbed starts near the
limits with references that pull beyond them, on the model (the RK45 plant) and on the MuJoCo `lab` robots that are
not the model, for every controller kind. Real parts throughout: composed configs, shipped networks, the compiled
classical NMPC, the real plants."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from pinnmpc.cli.structured import register_configs
from pinnmpc.controller.limits import JointLimits
from pinnmpc.plant.build import make_plant, simulated_arm
from pinnmpc.references.data import Reference
from pinnmpc.simulation.loop import run_loop
from pinnmpc.simulation.settings import validate_closed_loop
from pinnmpc.simulation.setup import build_controller
from pinnmpc.systems.settings import job_system

CONF = Path(__file__).resolve().parents[1] / "conf"
TOLERANCE = 1e-6  # rad a sample may lie past a limit (the bound)
# planar3 and the PowerCube have no joint limits (their joints turn all the way round): a user gives them some
USER_LIMITS = {  # {margin} filled in by composed()
    "planar3": "+system.control.joint_limits={{low:[-1.0,-1.2,-1.5],high:[1.0,0.9,1.5],weight:1.0e5,margin:{margin},"
    "lookahead:0.1}}",
    "powercube": "+system.control.joint_limits={{low:[-2.0,-1.0],high:[2.0,1.2],weight:1.0e5,margin:{margin},"
    "lookahead:0.2}}",
}
# per arm: a start a little inside two limits, and where its reference pulls those joints (beyond the limits)
NEAR = {
    "panda": ([0.0, 0.0, 0.0, -0.17, 0.0, 0.08, 0.0], [None, None, None, 0.33, None, -0.42, None]),
    "fr3": ([0.0, 0.0, 0.0, -0.22, 0.0, 0.54, 0.0], [None, None, None, 0.3, None, 0.0, None]),
    "planar3": ([0.0, 0.8, -1.4], [None, 1.3, -1.9]),
    "powercube": ([1.9, 1.1], [2.4, 1.6]),
}


def composed(arm: str, controller: str, *extra: str, margin: float = 0.01) -> Any:
    """The closed-loop config as the CLI composes it (arms without limits get USER_LIMITS with this margin)."""
    over = [f"system={arm}", f"controller={controller}", "progress=false", "plots=false", *extra]
    over += [USER_LIMITS[arm].format(margin=margin)] if arm in USER_LIMITS else []
    register_configs()
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("closed_loop", overrides=over)


def loop_parts(cfg: Any, arm: str) -> tuple[Any, Any, float, JointLimits]:
    """Controller, plant, control period and the controller's joint limits of a composed config of an arm."""
    system = job_system(cfg, validate_closed_loop)
    controller, _, tau = build_controller(cfg, system)
    plant = make_plant(simulated_arm(system, cfg.system), cfg.plant, tau, cfg.system.get("robots"), None)
    limits = JointLimits.from_config(cfg.controller.joint_limits, len(NEAR[arm][0]))
    return controller, plant, tau, limits


def pulling(arm: str, tau: float, steps: int) -> Reference:
    """A reference at rest that pulls two joints of the arm beyond their limits (the controller governs it)."""
    start, goal = NEAR[arm]
    q = np.array([s if g is None else g for s, g in zip(start, goal)], dtype=np.float64)
    x = np.concatenate([q, np.zeros_like(q)])
    return Reference(t=np.arange(steps) * tau, x=np.tile(x, (steps, 1)), name="pulling")


def onto_limits(tau: float, rise: float, hold: float = 1.5) -> Reference:
    """The Panda's joints 4 and 6 driven onto their limits in `rise` s (quintic, within the velocity limits from
    0.3 s on), then held there."""
    start = np.array([0.0, 0.0, 0.0, -0.5, 0.0, 0.5, 0.0])
    goal = start.copy()
    goal[3], goal[5] = -0.0698, -0.0175
    t = np.arange(0.0, rise + hold + 1e-9, tau)
    s = np.clip(t / rise, 0.0, 1.0)
    blend, rate = s**3 * (10 - 15 * s + 6 * s**2), 30 * s**2 * (1 - s) ** 2 / rise
    x = np.hstack([start + np.outer(blend, goal - start), np.outer(rate, goal - start)])
    return Reference(t=t, x=x, name="onto")


def excess(run: Any, limits: JointLimits) -> float:
    """How far the furthest sample of a closed loop lies past a limit (negative: inside)."""
    q = run.x[:, : len(limits.low)]
    return float(np.maximum(q - np.array(limits.high), np.array(limits.low) - q).max())


def perturbed_starts(reference: Reference, n: int, seed: int = 0) -> list[np.ndarray]:
    """n starts: the reference's and perturbations of its positions by 1e-12 to 1e-3 rad."""
    rng = np.random.default_rng(seed)
    nq = reference.x.shape[1] // 2
    starts = [reference.x[0].copy()]
    for _ in range(n - 1):
        x = reference.x[0].copy()
        x[:nq] += rng.uniform(-1.0, 1.0, nq) * 10.0 ** -rng.integers(3, 13)
        starts.append(x)
    return starts


SLOW = pytest.mark.slow  # a hundred closed loops per arm: make test-all


@pytest.mark.parametrize(
    ("arm", "controller", "starts"),
    [("panda", "nmpc", 8), ("panda", "casadi", 8), ("planar3", "nmpc", 8)]
    + [pytest.param(a, c, 100, marks=SLOW) for a in NEAR for c in ("nmpc", "casadi")],
)
def test_perturbed_starts_near_the_limits_never_cross_them(arm: str, controller: str, starts: int) -> None:
    """From the start and 99 perturbations of it (1e-12 to 1e-3 rad), a reference beyond two limits: the shipped
    controller stops every joint inside, on the true model (before the governor and the lookahead, plans chattered at
    the Panda's limits and crossed them by up to 2.7e-2 rad from some of these starts)."""
    controller_, plant, tau, limits = loop_parts(composed(arm, controller), arm)
    start = np.array(NEAR[arm][0] + [0.0] * len(NEAR[arm][0]))
    reference = pulling(arm, tau, 12 + controller_.horizon + 1)
    worst = []
    for x0 in perturbed_starts(Reference(t=reference.t, x=np.tile(start, (len(reference), 1)), name="s"), starts):
        controller_.reset()
        run = run_loop(controller_, plant, reference, x0=x0, progress=False)
        worst.append(excess(run, limits))
    assert max(worst) <= TOLERANCE, f"{sum(w > TOLERANCE for w in worst)} of {starts} starts crossed: {max(worst):.3g}"
    # and the arm does go to the edge the governed reference asks for: the test is not passed by staying away
    assert np.median(worst) > -limits.margin - 5e-3


@pytest.mark.parametrize("controller", ["nmpc", "exact", "casadi"])
@pytest.mark.parametrize("rise", [pytest.param(0.3, marks=SLOW), 1.0])  # the faster rise in the default run
def test_the_lab_robot_stays_inside_on_references_onto_the_limits(controller: str, rise: float) -> None:
    """The Panda's lab robot (a 1 kg load, motor inertia, dry friction the model leaves out), joints 4 and 6 driven
    onto their limits and held there, from perturbed starts: no sample past a limit, for every controller kind with
    its shipped settings (before: 2.1e-3 rad past for the network controllers, 2.4e-2 for the classical one)."""
    cfg = composed("panda", controller, "plant=mujoco", "plant.robot=lab")
    controller_, plant, tau, limits = loop_parts(cfg, "panda")
    reference = onto_limits(tau, rise)
    worst = []
    for x0 in perturbed_starts(reference, 3):
        controller_.reset()
        run = run_loop(controller_, plant, reference, x0=x0, progress=False)
        worst.append(excess(run, limits))
    assert max(worst) <= TOLERANCE, f"past a limit by {max(worst):.3g} rad"
    assert max(worst) > -0.02  # it reached the limits' margin


def test_planar3_lab_robot_stays_inside_user_limits() -> None:
    """planar3's lab robot (a load half the last link's mass) with limits a user gives it, a reference pulling two
    joints beyond them from rest 0.1 rad inside, with the network fine-tuned on the robot's logs (the recipe for a
    robot that is not the model; the nominal network's one-step miss there exceeds the margin: docs/design.md)."""
    checkpoint = Path(__file__).resolve().parents[1] / "pinnmpc" / "checkpoints" / "planar3-lab.pt"
    cfg = composed("planar3", "nmpc", "plant=mujoco", "plant.robot=lab", f"checkpoint={checkpoint}")
    controller_, plant, tau, limits = loop_parts(cfg, "planar3")
    reference = pulling("planar3", tau, 30)
    start = np.array(NEAR["planar3"][0] + [0.0] * 3)
    worst = []
    for x0 in perturbed_starts(Reference(t=reference.t, x=np.tile(start, (30, 1)), name="s"), 5):
        controller_.reset()
        worst.append(excess(run_loop(controller_, plant, reference, x0=x0, progress=False), limits))
    assert max(worst) <= TOLERANCE, f"past a limit by {max(worst):.3g} rad"


def test_a_reference_inside_the_margin_is_untouched_and_one_beyond_is_governed() -> None:
    """The governor moves only the positions past (limit - margin) onto it and zeroes their velocities."""
    limits = JointLimits([-1.0, -np.inf], [1.0, np.inf], 1e5, 0.1, 0.05)
    inside = np.array([[0.5, 7.0, 0.3, 0.2]])
    assert limits.governed(inside) is inside
    beyond = np.array([[1.5, 7.0, 0.3, 0.2], [-0.95, -9.0, -0.4, 0.1]])
    governed = limits.governed(beyond)
    np.testing.assert_array_equal(governed, [[0.9, 7.0, 0.0, 0.2], [-0.9, -9.0, 0.0, 0.1]])
    np.testing.assert_array_equal(beyond[0], [1.5, 7.0, 0.3, 0.2])  # the caller's reference is not changed


def test_the_lookahead_counts_the_velocity_towards_a_limit_only() -> None:
    """The checked position is q + T v towards the limit the joint moves to; away from it, q alone."""
    limits = JointLimits([-1.0], [1.0], 1e5, 0.1, 0.05)
    states = np.array([[0.85, 2.0], [0.85, -2.0], [-0.85, -2.0]])
    low, high = limits.ahead(states)
    np.testing.assert_allclose(high[:, 0], [0.95, 0.85, -0.85])
    np.testing.assert_allclose(low[:, 0], [0.85, 0.75, -0.95])
    np.testing.assert_array_equal(limits.reached(states[:, None]), [True, False, True])
    with pytest.raises(ValueError, match=r"joint_limits.lookahead=-1"):
        JointLimits([-1.0], [1.0], 1e5, 0.1, -1)
    with pytest.raises(ValueError, match=r"unknown keys \['look_ahead'\]"):
        JointLimits.from_config({"low": [-1], "high": [1], "weight": 1.0, "margin": 0.1, "look_ahead": 0.1}, 1)
