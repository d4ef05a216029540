"""Build an NMPC from its config section, validating every number before the first solve."""

from __future__ import annotations

from typing import Any

from pinnmpc.controller.nmpc import NMPC
from pinnmpc.controller.ocp import HorizonOCP
from pinnmpc.controller.solvers import make_solver
from pinnmpc.surrogate import Surrogate


def build_nmpc(cfg: Any, surrogate: Surrogate) -> NMPC:
    """NMPC from conf/controller: horizon, weights, bounds (null: the surrogate's input box), solver."""
    solver_options = dict(cfg.solvers.get(cfg.solver) or {})
    solver = make_solver(cfg.solver, **solver_options)
    ocp = HorizonOCP(surrogate, cfg.horizon, list(cfg.Q), list(cfg.R), None if cfg.R_rate is None else list(cfg.R_rate))
    low = surrogate.input_box.low if cfg.u_low is None else list(cfg.u_low)
    high = surrogate.input_box.high if cfg.u_high is None else list(cfg.u_high)
    return NMPC(ocp, solver, low, high, warm_start=cfg.warm_start)
