"""The classical NMPC's transcription on a trained network: the exported flow map x(tau) = f(x0, u)
(pinnmpc.surrogate.casadi_network, the weights as constants, CasADi's exact Jacobian) predicts each stage, in place
of RK4 on the model's equations. Everything else is the classical NMPC's own (multiple shooting, sqpmethod or its
real-time iteration with qrqp or HPIPM, the C it generates): the way a CasADi user would run the same network, a peer
for the network NMPC (the bench's `peers` section) on the same exported function."""

from __future__ import annotations

from typing import Any

import casadi as ca

from pinnmpc.controller.classical.ocp import CasadiOCP
from pinnmpc.surrogate.casadi_network import casadi_flow
from pinnmpc.surrogate.checkpoint import Surrogate


class NetworkOCP(CasadiOCP):
    """The NLP of CasadiOCP with F(x_k, u_k) the surrogate's exported flow map (controller.transcription=network)."""

    transcription = "network"

    def __init__(self, surrogate: Surrogate, source: str, system: Any, *problem: Any, **limits: Any) -> None:
        if abs(float(surrogate.tau) - float(system.tau)) > 1e-12 * float(system.tau):
            raise ValueError(
                f"controller.network runs over tau={surrogate.tau} s; the arm's control period is {system.tau} s"
            )
        self.surrogate, self.source = surrogate, source
        super().__init__(system, *problem, **limits)

    def _prepare(self, system: Any, rhs: ca.Function, coulomb_width: float | None, rk4_steps: int | None) -> None:
        """F and F_sens: the exported flow map and its Jacobian (no sub-steps to choose)."""
        self.rk4_steps = None
        self.F, self.F_sens = casadi_flow(self.surrogate, name="network_flow")

    @property
    def tag(self) -> str:
        """The transcription in a file name (two networks' C differs: the compiled cache keeps both apart)."""
        return "network"

    def describe(self) -> dict[str, Any]:
        """The transcription and the network, for metrics.json."""
        return {"transcription": self.transcription, "network": self.source}
