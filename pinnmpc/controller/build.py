"""Build an NMPC from its config section, validating every number before the first solve."""

from __future__ import annotations

from typing import Any

from omegaconf import DictConfig, OmegaConf

from pinnmpc.controller.nmpc import NMPC
from pinnmpc.controller.ocp import HorizonOCP
from pinnmpc.controller.solvers import make_solver
from pinnmpc.surrogate import Surrogate

OPTIONAL = {  # what a Python caller may leave out (conf/controller/nmpc.yaml sets all of it for the CLIs)
    "R_rate": None,
    "u_low": None,
    "u_high": None,
    "warm_start": True,
    "solver": "lifted_gauss_newton",
    "solvers": {},
    "disturbance": {},
    "joint_limits": None,
}


def build_nmpc(cfg: Any, surrogate: Surrogate) -> NMPC:
    """NMPC from conf/controller: horizon, weights, soft joint limits, bounds (null: the surrogate's input box),
    solver."""
    if isinstance(cfg, DictConfig):
        cfg = OmegaConf.to_container(cfg, resolve=True)  # plain values: config objects are slow in hot loops
    cfg = {**OPTIONAL, **cfg}
    solver = make_solver(cfg["solver"], **((cfg["solvers"] or {}).get(cfg["solver"]) or {}))
    ocp = HorizonOCP(surrogate, cfg["horizon"], cfg["Q"], cfg["R"], cfg["R_rate"], cfg["joint_limits"])
    low = surrogate.input_box.low if cfg["u_low"] is None else cfg["u_low"]
    high = surrogate.input_box.high if cfg["u_high"] is None else cfg["u_high"]
    d = cfg["disturbance"] or {}
    return NMPC(
        ocp,
        solver,
        low,
        high,
        warm_start=cfg["warm_start"],
        disturbance_gain=float(d.get("gain", 0.0)),
        disturbance_max=d.get("max_abs"),
    )
