"""`python -m pinnmpc.bench [overrides]`: the paper's cost and accuracy claims, measured properly on this machine,
for any system (`system=planar3 checkpoint=...`).

Sections (each switchable in conf/bench.yaml), one module each:
1. step: one-step cost x_k -> x_k+1 of the PINN against Euler, RK4 (numpy, torch, compiled C) and RK45, with the
   accuracy each one buys;
2. loops: closed-loop tracking per solver, plus the same controller on an RK4 model of the true dynamics and the
   configured controller on the system's other built-in references;
3. optimality: the gap of each solver's solutions to a tight multi-start L-BFGS-B reference solve;
4. scaling: OCP and one-step cost against horizon and batch size;
5. targets: the system's targets next to this run's numbers;
6. classical: the PINN controller against the classical CasADi NMPC on the true model, same protocol.
timing measures, report writes bench.md, run ties them together; bench.json, bench.md and PNG plots are written
(atomically) into the run dir.
"""

from pinnmpc.util.lazy import lazy_exports

__all__ = ["run_bench", "run_controller"]
__getattr__, __dir__ = lazy_exports(  # imported on first use: `python -m pinnmpc.bench --help` does not wait for torch
    __name__, {"run_bench": "pinnmpc.bench.run", "run_controller": "pinnmpc.bench.loops"}
)
