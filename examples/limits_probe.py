"""Probe of issue 63: closed loops from perturbed starts on a reference that brings joints onto their limits and
holds them there; counts samples past a limit (run: python examples/limits_probe.py panda nmpc lab 20)."""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np
from hydra import compose, initialize_config_dir

from pinnmpc.plant.build import make_plant, simulated_arm
from pinnmpc.references.data import Reference
from pinnmpc.simulation.loop import run_loop
from pinnmpc.simulation.setup import build_controller
from pinnmpc.util.settings import job_system, validate_closed_loop
from pinnmpc.util.structured import register_configs

CONF = Path(__file__).resolve().parents[1] / "conf"
PLANAR3_LIMITS = ([-1.0, -1.2, -1.5], [1.0, 0.9, 1.5])  # limits given to planar3 for the probe (it has none)


def compose_cfg(arm: str, controller: str, robot: str | None, extra: list[str] = ()) -> object:
    """The closed-loop config as the CLI composes it."""
    over = [f"system={arm}", f"controller={controller}", "progress=false", "plots=false", *extra]
    if robot:
        over += ["plant=mujoco", f"plant.robot={robot}"]
    if arm == "planar3":
        lo, hi = PLANAR3_LIMITS
        over += [f"+system.control.joint_limits={{low:{lo},high:{hi},weight:1.0e5,margin:0.01}}"]
    register_configs()
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("closed_loop", overrides=over)


def onto_limits(arm: str, tau: float, rise: float = 1.0, hold: float = 1.5) -> Reference:
    """Two joints driven onto a limit each in `rise` s (quintic blend), then held there."""
    if arm == "panda":
        start = np.array([0.0, 0.0, 0.0, -0.5, 0.0, 0.5, 0.0])
        goal = start.copy()
        goal[3], goal[5] = -0.0698, -0.0175  # joint 4 onto its upper, joint 6 onto its lower limit
    else:
        start = np.array([0.0, 0.3, 0.0])
        goal = np.array([0.0, 0.9, -1.5])
    t = np.arange(0.0, rise + hold + 1e-9, tau)
    s = np.clip(t / rise, 0.0, 1.0)
    blend, dblend = s**3 * (10 - 15 * s + 6 * s**2), 30 * s**2 * (1 - s) ** 2 / rise
    x = np.hstack([start + np.outer(blend, goal - start), np.outer(dblend, goal - start)])
    return Reference(t=t, x=x, name="onto_limits")


def main(arm: str, controller: str, robot: str | None, starts: int, steps: int, extra: list[str]) -> None:
    """Run the loops, print the worst excess and the samples past a limit."""
    cfg = compose_cfg(arm, controller, robot, extra)
    system = job_system(cfg, validate_closed_loop)
    ctrl, domain, tau = build_controller(cfg, system)
    limits = cfg.controller.joint_limits
    low, high = np.array(limits.low), np.array(limits.high)
    ref = onto_limits(arm, tau, float(os.environ.get("RISE", "1.0")))
    arm_sys = simulated_arm(system, cfg.system)
    plant = make_plant(arm_sys, cfg.plant, tau, cfg.system.get("robots"), None)
    rng = np.random.default_rng(0)
    worst, bad, errs, t0 = [], 0, [], time.perf_counter()
    for i in range(starts):
        x0 = ref.x[0] + (0 if i == 0 else rng.uniform(-1e-3, 1e-3, ref.x.shape[1]) * 10.0 ** -rng.integers(0, 9))
        run = run_loop(ctrl, plant, ref, x0=x0, max_steps=steps, progress=False)
        q = run.x[:, : len(low)]
        ex = np.maximum(q - high, low - q).max(-1)
        worst.append(ex.max())
        bad += int((ex > 1e-6).sum())
        errs.append(np.abs(run.x[-10:, : len(low)] - ref.x[len(run.x) - 10 : len(run.x), : len(low)]).mean())
    worst = np.array(worst)
    print(
        f"{arm} {controller} robot={robot} starts={starts} steps={steps}: worst excess {worst.max():.3g} rad, "
        f"starts past {int((worst > 1e-6).sum())}, samples past {bad}, final MAE {np.mean(errs):.3g}, "
        f"{time.perf_counter() - t0:.1f} s"
    )


if __name__ == "__main__":
    a = sys.argv[1:]
    main(a[0], a[1], None if a[2] == "model" else a[2], int(a[3]), int(a[4]) if len(a) > 4 else 60, a[5:])
