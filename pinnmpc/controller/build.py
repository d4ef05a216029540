"""Build an NMPC from its config section, validating every number before the first solve."""

from __future__ import annotations

from typing import Any

from pinnmpc.controller.base import checked_settings
from pinnmpc.controller.nmpc import NMPC
from pinnmpc.controller.ocp import HorizonOCP
from pinnmpc.controller.previous_input import PreviousInputNMPC, padded_weight
from pinnmpc.controller.settings import NetworkSettings
from pinnmpc.controller.solvers import make_solver
from pinnmpc.surrogate.checkpoint import Surrogate
from pinnmpc.surrogate.delayed_command import controller_flow
from pinnmpc.surrogate.flowmap import CompiledRK4, ExactValues, FlowMap, PriorOnly
from pinnmpc.surrogate.previous_input import PreviousInputFlow
from pinnmpc.systems.base import System
from pinnmpc.systems.previous_input import takes_previous_input


def prediction_model(cfg: NetworkSettings, surrogate: Surrogate, system: System | None) -> FlowMap:
    """What the OCP predicts with (controller.model): the surrogate alone (the PINN replaces integration), the
    true model's values, integrated by compiled RK4, with the surrogate's Jacobians (plans obey the true dynamics),
    or the surrogate's physics prior alone (what the network adds, measured)."""
    kind = cfg.model
    if kind == "surrogate":
        return surrogate
    if kind == "prior":
        return PriorOnly(surrogate)
    if system is None:
        raise ValueError("controller.model=exact_values needs the system's true model (build_nmpc(..., system=...))")
    steps = cfg.exact_rk4_steps
    if steps is None:
        from pinnmpc.controller.classical.ocp import stable_rk4_steps

        steps = stable_rk4_steps(system, surrogate.tau)
    return ExactValues(surrogate, CompiledRK4(system, surrogate.tau, surrogate.tau / steps))


def real_time_default(surrogate: Surrogate, trust: float | None = None) -> bool:
    """controller.rti=null: the real-time iteration (one lifted step per sample) for a
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
    """NMPC from its settings (NetworkSettings, or a config node or dict of them: conf/controller/nmpc.yaml), each
    checked; what a Python caller leaves out takes NetworkSettings' default, as the commands do. Input bounds null:
    the surrogate's input box; model=exact_values needs the system."""
    surrogate = controller_flow(surrogate)  # a network split at its command_delay takes (u, u_prev)
    previous = takes_previous_input(surrogate)  # its inputs are (u, u_prev): the OCP's states carry u_prev
    flow = PreviousInputFlow(surrogate) if previous else surrogate
    cfg = checked_settings(NetworkSettings, cfg, {"nx": len(surrogate.state_names), "nu": len(flow.input_names)})
    assert isinstance(cfg, NetworkSettings)
    if previous and cfg.model != "surrogate":
        raise ValueError(
            f"controller.model={cfg.model} with a network that takes the previous input: expected surrogate (the true "
            "model and the prior take the arm's inputs alone)"
        )
    options = dict((cfg.solvers or {}).get(cfg.solver) or {})
    if cfg.solver == "lifted_gauss_newton":
        if options.get("rti_trust") is None:
            options["rti_trust"] = trust_default(surrogate, cfg.rti_trust)
        options["rti"] = real_time_default(surrogate, options["rti_trust"]) if cfg.rti is None else cfg.rti
    solver = make_solver(cfg.solver, **options)
    extra = flow.nu if previous else 0  # u_prev's states: untracked, never disturbed
    Q = padded_weight(cfg.Q, extra) if previous else cfg.Q
    rate = cfg.R_rate_previous_input if previous and cfg.R_rate is None else cfg.R_rate
    ocp = HorizonOCP(prediction_model(cfg, flow, system), cfg.horizon, Q, cfg.R, rate, cfg.joint_limits)
    prepare = getattr(solver, "prepare", None)
    if prepare is not None:  # what the solver compiles for this OCP, built before the first sample
        prepare(ocp)
    low = flow.input_box.low if cfg.u_low is None else cfg.u_low
    high = flow.input_box.high if cfg.u_high is None else cfg.u_high
    d = cfg.disturbance
    bound = d.max_abs if d.max_abs is None or not previous else [*d.max_abs, *[0.0] * extra]
    return (PreviousInputNMPC if previous else NMPC)(
        ocp,
        solver,
        low,
        high,
        warm_start=cfg.warm_start,
        disturbance_gain=float(d.gain),
        disturbance_max=bound,
        disturbance_notch=notch_default(surrogate) if d.notch is None else d.notch,
        notch_when_late=d.notch is None,
    )
