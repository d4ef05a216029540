"""A closed loop in a few lines: the shipped planar3 network as the NMPC's model, the RK45 plant as the robot."""

import numpy as np

from pinnmpc import load_surrogate, load_system
from pinnmpc.controller.build import build_nmpc
from pinnmpc.plant import ScipyPlant
from pinnmpc.references import Reference
from pinnmpc.simulation import run_loop

system = load_system("planar3")  # the arm: dynamics, boxes, names
flow = load_surrogate(system="planar3")  # the learned flow map x(tau) = f(x0, u)
controller = build_nmpc({"horizon": 5, "Q": [1, 1, 1, 0, 0, 0], "R": [1e-8, 1e-7, 1e-6]}, flow, system)
plant = ScipyPlant(system, flow.tau)  # the simulated robot
t = np.arange(0.0, 4.0, flow.tau)
q = 0.3 * np.sin(np.outer(t, [0.5, 0.8, 1.1]))  # joint angles to follow, rad
reference = Reference(t, np.hstack([q, np.gradient(q, t, axis=0)]), "sine")
result = run_loop(controller, plant, reference, progress=False)
error = np.abs(result.x[:, :3] - reference.x[: len(result.x), :3]).mean(axis=0).max()
print(f"{result.status}: worst joint-angle MAE {error:.2e} rad")
