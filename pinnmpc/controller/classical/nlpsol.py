"""A compiled or symbolic CasADi nlpsol called through CasADi's buffer interface, and what one solve returned."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import casadi as ca
import numpy as np

if TYPE_CHECKING:
    from pinnmpc.controller.classical.ocp import CasadiOCP

SUCCESS = {  # return statuses that count as converged, per plugin
    "ipopt": {"Solve_Succeeded", "Solved_To_Acceptable_Level"},
    "sqpmethod": {"Solve_Succeeded"},
    "fatrop": {"Solve_Succeeded"},
}
QUIET = {  # options that silence each plugin
    "ipopt": {"ipopt": {"print_level": 0, "sb": "yes"}, "print_time": False},
    "sqpmethod": {
        "print_time": False,
        "print_header": False,
        "print_iteration": False,
        "print_status": False,
    },
    "fatrop": {"fatrop": {"print_level": 0}, "print_time": False},
}


@dataclass
class Solution:
    """What one solve returned; the arrays are the solver's output buffers (copy what you keep)."""

    w: np.ndarray
    lam_x: np.ndarray
    lam_g: np.ndarray
    cost: float
    success: bool
    iterations: int
    status: str


class NlpSolver:
    """An nlpsol evaluated through CasADi's buffer interface: numpy arrays in and out, no copies per call."""

    def __init__(
        self,
        ocp: CasadiOCP,
        solver: ca.Function,
        flow: ca.Function,
        success: set[str],
        functions: dict[str, ca.Function] | None = None,
    ) -> None:
        self.solver, self._success = solver, success
        self.functions = functions or {}  # further functions of the same library, by name
        self.w0, self.p = np.zeros(ocp.nw), np.zeros(ocp.np)
        self.lam_x0, self.lam_g0 = np.zeros(ocp.nw), np.zeros(ocp.ng)
        self._args = [self.w0, self.p, ocp.lbw.copy(), ocp.ubw.copy(), ocp.lbg.copy(), ocp.ubg.copy()]
        self._args += [self.lam_x0, self.lam_g0]
        self.w, self.cost, self.g = np.zeros(ocp.nw), np.zeros(1), np.zeros(ocp.ng)
        self.lam_x, self.lam_g, self.lam_p = np.zeros(ocp.nw), np.zeros(ocp.ng), np.zeros(ocp.np)
        self._res = [self.w, self.cost, self.g, self.lam_x, self.lam_g, self.lam_p]
        self._buf, self._trigger = solver.buffer()
        for i, a in enumerate(self._args):
            self._buf.set_arg(i, memoryview(a))
        for i, r in enumerate(self._res):
            self._buf.set_res(i, memoryview(r))
        # the flow F(x, u) from a guess of the transcription's unknowns, for the offset-free estimator's prediction
        self.flow_x, self.flow_u, self.flow_out = np.zeros(ocp.nx), np.zeros(ocp.nu), np.zeros(ocp.nx)
        self.flow_z = np.zeros(ocp.nz)
        self._cold_flow = ocp.F if ocp.nz else None  # from scratch, where there is no guess
        self._fbuf, self._ftrigger = flow.buffer()
        for i, a in enumerate((self.flow_x, self.flow_u, self.flow_z)):
            self._fbuf.set_arg(i, memoryview(a))
        self._fbuf.set_res(0, memoryview(self.flow_out))

    def __call__(self) -> Solution:
        """Solve from the current w0, lam_x0, lam_g0 and p (fill them in place first)."""
        self._trigger()
        stats = self._buf.stats()
        status = str(stats.get("return_status", "unknown"))
        return Solution(
            w=self.w,
            lam_x=self.lam_x,
            lam_g=self.lam_g,
            cost=float(self.cost[0]),
            success=bool(stats.get("success", False)) or status in self._success,
            iterations=int(stats.get("iter_count", 0)),
            status=status,
        )

    def flow(self, x: np.ndarray, u: np.ndarray, guess: np.ndarray | None = None) -> np.ndarray:
        """F(x, u) over one tau (undisturbed), a copy; guess: the transcription's unknowns to start from (the plan's),
        None: from scratch."""
        if guess is None and self._cold_flow is not None:
            return np.asarray(self._cold_flow(x, u), dtype=np.float64).reshape(-1)
        self.flow_x[:] = x
        self.flow_u[:] = u
        self.flow_z[:] = 0.0 if guess is None else guess
        self._ftrigger()
        return self.flow_out.copy()
