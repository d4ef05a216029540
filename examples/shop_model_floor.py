"""How close could a model track a robot the model is not? The network controller predicts each period with the
robot's own MuJoCo dynamics (its values; the actuator's lag starting at the input applied before) and a network's
Jacobians (a network given the previous input: its own; a plain one: none in u_prev), on that robot as the plant:
what this controller and its estimator allow once the model is exact, the floor of any network fine-tuned on it.

    python examples/shop_model_floor.py --reference random-101                 # docs/robot.md, the shop robot
    python examples/shop_model_floor.py --reference random-101 --no-estimator
    python examples/shop_model_floor.py --reference random-101 --converged   # each sample solved fully
    python examples/shop_model_floor.py --system panda --checkpoint pinnmpc/checkpoints/panda-shop.pt --steps 120
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from pinnmpc import load_surrogate
from pinnmpc.cli.structured import register_configs
from pinnmpc.controller.build import build_nmpc
from pinnmpc.plant.build import make_plant
from pinnmpc.simulation import run_loop
from pinnmpc.simulation.setup import system_reference
from pinnmpc.surrogate.previous_input import RowValuesFlow
from pinnmpc.systems.registry import build_system

CONF = Path(__file__).resolve().parents[1] / "conf"


def robot_rows(robot: Any) -> Callable[..., np.ndarray]:
    """The robot's own period for each row of x0 (B, nx) and (u, u_prev) (B, 2 nu): the lag's filter starts at u_prev
    (MujocoPlant.period_from)."""

    def rows(x0: np.ndarray, inputs: np.ndarray, tau: float) -> np.ndarray:
        """x(tau) of each row."""
        m = inputs.shape[-1] // 2
        return np.stack([robot.period_from(x, p[:m], p[m:]) for x, p in zip(x0, inputs)])

    return rows


def main() -> None:
    """One closed loop on the robot with its own dynamics as the model; prints the worst joint-angle MAE."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--system", default="planar3", help="an arm with a robot of that name (system.robots)")
    parser.add_argument("--robot", default="shop", help="the robot (plant=mujoco plant.robot=...)")
    parser.add_argument("--checkpoint", default="pinnmpc/checkpoints/planar3-shop.pt", help="the Jacobians' network")
    parser.add_argument("--reference", default="default", help="a built-in reference of the arm")
    parser.add_argument("--no-estimator", action="store_true", help="controller.disturbance.gain=0")
    parser.add_argument("--converged", action="store_true", help="controller.rti=false: each sample solved fully")
    parser.add_argument("--steps", type=int, default=200, help="control periods")
    args = parser.parse_args()
    register_configs()
    overrides = [f"system={args.system}", "plant=mujoco", f"plant.robot={args.robot}"]
    overrides += [f"reference.name={args.reference}", "progress=false"]
    with initialize_config_dir(config_dir=str(CONF), version_base=None):
        cfg = compose(config_name="closed_loop", overrides=overrides)
    system = build_system(cfg.system)
    reference = system_reference(cfg, system, system.tau)
    plant, model = (make_plant(system, cfg.plant, system.tau, cfg.system.get("robots")) for _ in range(2))
    flow = RowValuesFlow(robot_rows(model), load_surrogate(args.checkpoint), system)
    settings = OmegaConf.to_container(cfg.controller, resolve=True)
    settings = {k: v for k, v in settings.items() if k not in ("kind", "checkpoint")}
    if args.no_estimator:
        settings["disturbance"] = {**settings["disturbance"], "gain": 0.0}
    if args.converged:
        settings["rti"] = False
    controller = build_nmpc(settings, flow, system)
    result = run_loop(controller, plant, reference, max_steps=args.steps, progress=False)
    n = system.nq
    error = np.abs(result.x[:, :n] - reference.x[: len(result.x), :n]).mean(axis=0).max()
    print(f"{result.status}: worst joint-angle MAE {error:.3e} rad over {len(result.x) - 1} periods")


if __name__ == "__main__":
    main()
