"""Build an NMPC from its config section, validating every number before the first solve."""

from __future__ import annotations

from typing import Any

from omegaconf import DictConfig, OmegaConf

from pinnmpc.controller.nmpc import NMPC
from pinnmpc.controller.ocp import HorizonOCP
from pinnmpc.controller.solvers import make_solver
from pinnmpc.controller.solvers.lifted import valid_trust
from pinnmpc.surrogate.checkpoint import Surrogate
from pinnmpc.surrogate.flowmap import CompiledRK4, ExactValues, FlowMap, PriorOnly
from pinnmpc.systems.base import System

MODELS = ("surrogate", "exact_values", "prior")  # controller.model: what the OCP predicts with
GAUSS_NEWTON = ("lifted_gauss_newton", "gauss_newton")  # the solvers that take a numpy model's Jacobians

REQUIRED = ("horizon", "Q", "R")  # what every NMPC config names
OPTIONAL = {  # what a Python caller may leave out (conf/controller/nmpc.yaml sets all of it for the CLIs)
    "R_rate": None,
    "u_low": None,
    "u_high": None,
    "warm_start": True,
    "solver": "lifted_gauss_newton",
    "solvers": {},
    "disturbance": {},
    "joint_limits": None,
    "model": "surrogate",
    "exact_rk4_steps": None,
    "rti_trust": None,
}


def prediction_model(cfg: dict[str, Any], surrogate: Surrogate, system: System | None) -> FlowMap:
    """What the OCP predicts with (controller.model): the surrogate alone (the PINN replaces integration), the
    true model's values, integrated by compiled RK4, with the surrogate's Jacobians (plans obey the true dynamics),
    or the surrogate's physics prior alone (what the network adds, measured)."""
    kind = cfg["model"]
    if kind not in MODELS:
        raise ValueError(f"controller.model={kind!r}; expected one of {list(MODELS)}")
    if kind == "surrogate":
        return surrogate
    if cfg["solver"] not in GAUSS_NEWTON:
        raise ValueError(
            f"controller.model={kind} needs a Gauss-Newton solver {list(GAUSS_NEWTON)} (its values are numpy, "
            f"not differentiable by torch), got controller.solver={cfg['solver']!r}"
        )
    if kind == "prior":
        return PriorOnly(surrogate)
    if system is None:
        raise ValueError("controller.model=exact_values needs the system's true model (build_nmpc(..., system=...))")
    steps = cfg["exact_rk4_steps"]
    if steps is None:
        from pinnmpc.controller.classical.ocp import stable_rk4_steps

        steps = stable_rk4_steps(system, surrogate.tau)
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ValueError(f"controller.exact_rk4_steps={steps!r}; expected a whole number >= 1 or null (automatic)")
    return ExactValues(surrogate, CompiledRK4(system, surrogate.tau, surrogate.tau / steps))


def real_time_default(surrogate: Surrogate, trust: float | None = None) -> bool:
    """controller.solvers.lifted_gauss_newton.rti=null: the real-time iteration (one lifted step per sample) for a
    network trained on the model alone, whose flow is smooth: it tracks within 1.1x of the converged solve at a
    fraction of its time (docs/results.md), and for one fine-tuned on robot logs against an identified model's
    residual and anchors (`physics` in its meta), which keep its flow near that smooth. A network fine-tuned on the
    logs alone (`robot_logs` in its meta) has learnt the robot's dry friction, which one step per sample does not
    follow everywhere: the real-time iteration only with a trust bound (`trust`, see trust_default), else the
    converged solve; the converged solve for any other flow map (a true model given as the model)."""
    meta = getattr(surrogate, "meta", None)
    if not isinstance(meta, dict):
        return False
    return not meta.get("robot_logs") or bool(meta.get("physics")) or trust is not None


def trust_default(surrogate: Surrogate, arm_trust: float | None) -> float | None:
    """controller.solvers.lifted_gauss_newton.rti_trust=null: the arm's bound (controller.rti_trust, from
    system.control.rti_trust) for a network fine-tuned on robot logs, whose learnt stick-slip makes a few real-time
    steps jump where its linearisation does not reach (one full solve there re-anchors the plan: docs/results.md);
    none for a network trained on the model alone (its numbers stay as measured)."""
    meta = getattr(surrogate, "meta", None)
    return arm_trust if isinstance(meta, dict) and meta.get("robot_logs") else None


def notch_default(surrogate: Surrogate) -> bool:
    """controller.disturbance.notch=null: on for a network fine-tuned on robot logs (`robot_logs` in its meta), which
    runs on a robot whose dry friction sticks and slips at the control rate, so its prediction errors can flip sign
    every sample (the Panda's lab robot: docs/results.md); off for a network trained on the model alone, where the
    notch's half-sample lag costs (the nominal arms track 10-30% worse with it)."""
    meta = getattr(surrogate, "meta", None)
    return isinstance(meta, dict) and bool(meta.get("robot_logs"))


def build_nmpc(cfg: Any, surrogate: Surrogate, system: System | None = None) -> NMPC:
    """NMPC from conf/controller: horizon, weights, soft joint limits, bounds (null: the surrogate's input box),
    solver, prediction model (exact_values needs the system)."""
    if isinstance(cfg, DictConfig):
        cfg = OmegaConf.to_container(cfg, resolve=True)  # plain values: config objects are slow in hot loops
    missing = [key for key in REQUIRED if key not in cfg]
    unknown = sorted(set(cfg) - set(REQUIRED) - set(OPTIONAL) - {"kind"})
    if missing or unknown:
        what = f"lacks {missing}" if missing else f"has unknown keys {unknown}"
        raise ValueError(f"the controller config {what}; expected {list(REQUIRED)} and any of {list(OPTIONAL)}")
    cfg = {**OPTIONAL, **cfg}
    trust = cfg["rti_trust"]
    if trust is not None and not valid_trust(trust):
        raise ValueError(
            f"controller.rti_trust={trust!r} (system.control.rti_trust); expected a fraction of the input box's "
            "width > 0 or null"
        )
    options = dict((cfg["solvers"] or {}).get(cfg["solver"]) or {})
    if cfg["solver"] == "lifted_gauss_newton":
        if options.get("rti_trust") is None:
            options["rti_trust"] = trust_default(surrogate, cfg["rti_trust"])
        if options.get("rti") is None:
            options["rti"] = real_time_default(surrogate, options["rti_trust"])
    solver = make_solver(cfg["solver"], **options)
    ocp = HorizonOCP(
        prediction_model(cfg, surrogate, system), cfg["horizon"], cfg["Q"], cfg["R"], cfg["R_rate"], cfg["joint_limits"]
    )
    low = surrogate.input_box.low if cfg["u_low"] is None else cfg["u_low"]
    high = surrogate.input_box.high if cfg["u_high"] is None else cfg["u_high"]
    d = cfg["disturbance"] or {}
    notch = d.get("notch")
    return NMPC(
        ocp,
        solver,
        low,
        high,
        warm_start=cfg["warm_start"],
        disturbance_gain=float(d.get("gain", 0.0)),
        disturbance_max=d.get("max_abs"),
        disturbance_notch=notch_default(surrogate) if notch is None else notch,
    )
