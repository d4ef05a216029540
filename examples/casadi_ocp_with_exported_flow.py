"""Your own CasADi optimal control problem with the learned flow map as its discrete dynamics.

The shipped planar3 network is exported once (`python -m pinnmpc.export system=planar3 out=DIR` does the same from
the shell), loaded back with casadi.Function.load, and used in an Opti problem: move the arm from rest to a target
configuration and hold it there, inputs and states within the box the network was trained on.
Run: python examples/casadi_ocp_with_exported_flow.py [folder with flow.casadi]
"""

import json
import sys
import tempfile
from pathlib import Path

import casadi as ca
import numpy as np

from pinnmpc.surrogate.checkpoint import shipped
from pinnmpc.surrogate.export import export

HORIZON = 10  # steps of tau (planar3: 0.1 s each)
Q_TARGET = [0.4, -0.3, 0.2]  # joint angles to reach and hold, rad
VELOCITY_WEIGHT = 1e-2  # cost of each squared joint velocity, per step, against the squared angle error in rad
INPUT_WEIGHT = 1e-6  # cost of each squared input (N m), per step


def load_flow(folder: Path) -> tuple[ca.Function, dict]:
    """f(x0, u) -> x(tau) on column vectors, and what export.json says about it (the training box)."""
    return ca.Function.load(str(folder / "flow.casadi")), json.loads((folder / "export.json").read_text())


if len(sys.argv) > 1:  # a folder exported before
    f, info = load_flow(Path(sys.argv[1]))
else:
    with tempfile.TemporaryDirectory() as tmp:
        export(shipped("planar3"), "casadi", Path(tmp) / "planar3", points=2000)  # checked against torch as written
        f, info = load_flow(Path(tmp) / "planar3")
(x_low, x_high), (u_low, u_high) = info["state_box"], info["input_box"]
nx, nu, n_q = len(x_low), len(u_low), len(Q_TARGET)

opti = ca.Opti()
x, u = opti.variable(nx, HORIZON + 1), opti.variable(nu, HORIZON)
x_start = opti.parameter(nx)
target = ca.DM(Q_TARGET)
opti.subject_to(x[:, 0] == x_start)
cost = 0
for k in range(HORIZON):
    opti.subject_to(x[:, k + 1] == f(x[:, k], u[:, k]))  # the learned dynamics
    opti.subject_to(opti.bounded(u_low, u[:, k], u_high))
    opti.subject_to(opti.bounded(x_low, x[:, k + 1], x_high))
    cost += ca.sumsqr(x[:n_q, k + 1] - target) + VELOCITY_WEIGHT * ca.sumsqr(x[n_q:, k + 1])
    cost += INPUT_WEIGHT * ca.sumsqr(u[:, k])
opti.minimize(cost)
opti.set_value(x_start, np.zeros(nx))
opti.solver("ipopt", {"print_time": False}, {"print_level": 0, "sb": "yes", "hessian_approximation": "limited-memory"})
solution = opti.solve()
x_plan, u_plan = solution.value(x), solution.value(u)
error = np.abs(x_plan[:n_q, -1] - np.asarray(Q_TARGET)).max()
print(f"{solution.stats()['return_status']}: final joint-angle error {error:.2e} rad, first input {u_plan[:, 0]}")
