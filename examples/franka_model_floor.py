"""How close could a model track franky-sim? The NMPC predicts each period under franky's ramp from the last command
to the new one (each joint at franky's acceleration limit, from `--ramp-start` s into the period) with franky-sim's
own MuJoCo FR3, run in this process with the gains plant=franka serves it (1 ms ticks, its servo law), or with a
system's arm (`--model`: a name or a .yaml, such as identify's) integrated under that ramp; its Jacobians are the
shipped fr3.pt's. The plant is the real franky-sim through libfranka (plant=franka's defaults).

    python examples/franka_model_floor.py --reference random-101            # docs/franka.md, "what the loop allows"
    python examples/franka_model_floor.py --reference random-101 --no-ramp  # the physics alone
    python examples/franka_model_floor.py --reference random-101 --model outputs/identify/fr3_sim.yaml
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import casadi as ca
import mujoco
import numpy as np
import pinocchio as pin
from franky_sim.mujoco_simulator import MujocoSimulator
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from pinnmpc import load_surrogate
from pinnmpc.cli.structured import register_configs
from pinnmpc.controller.build import build_nmpc
from pinnmpc.plant.build import make_plant
from pinnmpc.plant.integrators import rk4_step
from pinnmpc.simulation import run_loop
from pinnmpc.simulation.setup import system_reference
from pinnmpc.surrogate.previous_input import RowValuesFlow
from pinnmpc.systems.compiled import BatchedFunction, compile_functions
from pinnmpc.systems.registry import build_system, load_system

CONF = Path(__file__).resolve().parents[1] / "conf"
TICK = 1e-3  # franky-sim's physics step and libfranka's command rate, s


def ramp_reach(acceleration: np.ndarray, ramp_start: float | None, at: float) -> np.ndarray | float:
    """How far franky's ramp has moved each joint's command from the last one `at` s into the period (inf: no ramp)."""
    return np.inf if ramp_start is None else acceleration * max(0.0, at - ramp_start)


class FrankySimPhysics:
    """franky-sim's FR3 (MuJoCo, its pinocchio model for the servo's bias torques) stepped here, tick by tick."""

    def __init__(self, q0: np.ndarray, gains: np.ndarray, acceleration: np.ndarray, ramp_start: float | None) -> None:
        self._context = MujocoSimulator()
        sim = self._context.__enter__()
        self.robot = sim.add_robot(initial_q=tuple(q0), kv=tuple(gains))
        sim.start()
        self.model, self.data = sim.model, sim.data
        self.arm_q, self.arm_v = list(self.robot._qpos_addrs), list(self.robot._dof_addrs)
        self.fingers = list(self.robot._finger_qpos_addrs)
        self.finger_q = self.data.qpos[self.fingers].copy()
        self.pin_model, self.pin_data = self.robot._BaseRobot__model, self.robot._BaseRobot__data
        self.gains, self.acceleration, self.ramp_start = gains, acceleration, ramp_start
        self.low, self.high = np.asarray(self.robot.torque_limit_low), np.asarray(self.robot.torque_limit_high)

    def period(self, x0: np.ndarray, previous: np.ndarray, command: np.ndarray, tau: float) -> np.ndarray:
        """(q, v) a period after x0 while the servo's command ramps from `previous` to `command` (ramp_start None:
        the new command from the first tick)."""
        d = self.data
        d.qvel[:] = 0.0
        d.qpos[self.arm_q], d.qvel[self.arm_v], d.qpos[self.fingers] = x0[:7], x0[7:], self.finger_q
        d.qacc_warmstart[:] = 0.0
        mujoco.mj_forward(self.model, d)
        for i in range(round(tau / TICK)):
            reach = ramp_reach(self.acceleration, self.ramp_start, i * TICK)
            target = previous + np.clip(command - previous, -reach, reach)
            q, v = d.qpos[self.arm_q], d.qvel[self.arm_v]
            gravity = pin.computeGeneralizedGravity(self.pin_model, self.pin_data, q).copy()
            bias = pin.nonLinearEffects(self.pin_model, self.pin_data, q, v) - gravity
            d.qfrc_applied[self.arm_v] = np.clip(self.gains * (target - v) + bias, self.low, self.high) + gravity
            self.robot._pre_step()  # the hand's own finger servo
            mujoco.mj_step(self.model, d)
        return np.concatenate([d.qpos[self.arm_q], d.qvel[self.arm_v]])

    def rows(self, x0: np.ndarray, inputs: np.ndarray, tau: float) -> np.ndarray:
        """period() of each row of x0 (B, 14) and (u, u_prev) (B, 14)."""
        return np.stack([self.period(x, p[7:], p[:7], tau) for x, p in zip(x0, inputs)])


class RampedArm:
    """A system's arm integrated under the ramped command by RK4 sub-steps of h (the command at each one's middle),
    compiled: rows(x0, (u, u_prev), tau) -> x(tau)."""

    def __init__(self, system: Any, acceleration: np.ndarray, ramp_start: float | None, tau: float, h: float) -> None:
        nx, nu = len(system.state_names), len(system.input_names)
        x, inputs, v = ca.MX.sym("x", nx), ca.MX.sym("u", 2 * nu), ca.MX.sym("v", nu)
        one = ca.Function("one", [x, v], [rk4_step(system.casadi_rhs(), x, v, h, h)])
        u, previous, x1 = inputs[:nu], inputs[nu:], x
        for i in range(round(tau / h)):
            reach = ramp_reach(acceleration, ramp_start, (i + 0.5) * h)
            x1 = one(x1, previous + ca.fmin(ca.fmax(u - previous, -reach), reach))
        start = "none" if ramp_start is None else f"{ramp_start * 1e4:.0f}"
        step = ca.Function(f"{system.name}_ramped_{start}_{h * 1e6:.0f}", [x, inputs], [x1])
        self._step = BatchedFunction(compile_functions(step.name(), [step])[step.name()])

    def rows(self, x0: np.ndarray, inputs: np.ndarray, tau: float) -> np.ndarray:
        """x(tau) of each row."""
        return self._step(np.ascontiguousarray(x0), np.ascontiguousarray(inputs))[0]


def main() -> None:
    """One closed loop on franky-sim with the model above; prints the worst joint-angle MAE."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference", default="default", help="a built-in reference of the FR3")
    parser.add_argument("--ramp-start", type=float, default=0.002, help="s into the period franky's ramp begins")
    parser.add_argument("--no-ramp", action="store_true", help="the model's command steps at the period's start")
    parser.add_argument("--no-estimator", action="store_true", help="controller.disturbance.gain=0")
    parser.add_argument("--steps", type=int, default=200, help="control periods")
    parser.add_argument("--model", default=None, help="a system (name or .yaml) instead of franky-sim's physics")
    parser.add_argument("--substep", type=float, default=5e-4, help="--model's RK4 step, s")
    args = parser.parse_args()
    register_configs()
    overrides = ["system=fr3", "plant=franka", f"reference.name={args.reference}", "progress=false"]
    with initialize_config_dir(config_dir=str(CONF), version_base=None):
        cfg = compose(config_name="closed_loop", overrides=overrides)
    system = build_system(cfg.system)
    reference = system_reference(cfg, system, system.tau)
    plant = make_plant(system, cfg.plant, system.tau)
    try:
        ramp_start, acceleration = None if args.no_ramp else args.ramp_start, np.asarray(plant.command_acceleration)
        if args.model is None:
            model: Any = FrankySimPhysics(reference.x[0, :7], np.asarray(system.servo_gain), acceleration, ramp_start)
        else:
            model = RampedArm(load_system(args.model), acceleration, ramp_start, system.tau, args.substep)
        flow = RowValuesFlow(model.rows, load_surrogate(system="fr3"), system)
        controller_cfg = OmegaConf.to_container(cfg.controller, resolve=True)
        settings = {k: v for k, v in controller_cfg.items() if k not in ("kind", "checkpoint")}
        if args.no_estimator:
            settings["disturbance"] = {**settings["disturbance"], "gain": 0.0}
        controller = build_nmpc(settings, flow, system)
        x0 = plant.start(reference.x[0])
        result = run_loop(controller, plant, reference, x0=x0, max_steps=args.steps, progress=False)
    finally:
        plant.close()
    error = np.abs(result.x[:, :7] - reference.x[: len(result.x), :7]).mean(axis=0).max()
    print(f"{result.status}: worst joint-angle MAE {error:.3e} rad, libfranka errors {plant.errors}")


if __name__ == "__main__":
    main()
