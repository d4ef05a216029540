"""A closed loop's parts from its config: controller, reference and start state, each checked before the run."""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf

from pinnmpc.controller.base import Controller
from pinnmpc.controller.build import build_nmpc
from pinnmpc.controller.classical.settings import ClassicalSettings
from pinnmpc.controller.registry import build_registered, register_controller
from pinnmpc.controller.settings import NetworkSettings
from pinnmpc.references.files import Reference, load_reference, resolve_reference_path
from pinnmpc.simulation.loop import diverged, divergence_box, far_outside
from pinnmpc.surrogate.checkpoint import load_surrogate
from pinnmpc.systems.base import Box, System
from pinnmpc.util.checks import SettingError

log = logging.getLogger(__name__)


def build_controller(cfg: DictConfig, system: System) -> tuple[Controller, Box | None, float]:
    """The controller of the registered kind controller.kind (pinnmpc.controller.registry; default pinn), the state
    box its model is valid in (None: everywhere) and tau."""
    return build_registered(cfg, system)


@register_controller("pinn", NetworkSettings)
def build_pinn_controller(
    settings: NetworkSettings, cfg: DictConfig, system: System
) -> tuple[Controller, Box | None, float]:
    """NMPC on the surrogate (checkpoint, or the one shipped for this system): nmpc.yaml, exact.yaml."""
    surrogate = load_surrogate(
        cfg.checkpoint, system=system.name if cfg.checkpoint is None else None, state_names=system.state_names
    )
    check_input_bounds(cfg, surrogate.input_box)
    return build_nmpc(settings, surrogate, system), surrogate.domain, surrogate.tau


@register_controller("casadi", ClassicalSettings)
def build_classical_controller(
    settings: ClassicalSettings, cfg: DictConfig, system: System
) -> tuple[Controller, Box | None, float]:
    """The classical NMPC on the true model (compiled, pinnmpc.controller.classical.nmpc): casadi.yaml."""
    from pinnmpc.controller.classical.nmpc import build_casadi_nmpc  # casadi's compiled solvers load only when asked

    return build_casadi_nmpc(settings, system), None, system.tau


def warn_long_horizon(cfg: DictConfig) -> None:
    """A horizon far beyond the usual few steps makes every solve slow and often unconverged (a plan the loop
    still applies): say so before the run rather than after minutes of it."""
    horizon, limit = int(cfg.controller.horizon), cfg.get("long_horizon")
    if limit is not None and horizon > int(limit):
        log.warning(
            "controller.horizon=%d is above long_horizon=%d: each solve costs H^2 to H^3 and may stop at its "
            "iteration cap unconverged; expected a horizon of a few to a few dozen steps (raise long_horizon to "
            "silence this)",
            horizon, int(limit),
        )  # fmt: skip


def arm_differences(meta: dict[str, Any] | None, cfg: DictConfig) -> list[str]:
    """system.dynamics keys whose value in the network's training config differs from this run's (names alone do
    not tell two arms apart: a checkpoint of a j1/j2 arm loads on any other); empty where the meta has none."""
    trained = ((meta or {}).get("config") or {}).get("system", {}).get("dynamics")
    if not isinstance(trained, dict) or "dynamics" not in cfg.system:
        return []
    now = OmegaConf.to_container(cfg.system.dynamics, resolve=True)
    if isinstance(trained.get("urdf"), str) and isinstance(now.get("urdf"), str):  # one file, however it was named
        from pinnmpc.systems.urdf import portable_urdf

        trained, now = {**trained, "urdf": portable_urdf(trained["urdf"])}, {**now, "urdf": portable_urdf(now["urdf"])}
    return sorted(k for k in set(trained) & set(now) if trained[k] != now[k])


def bounds_outside(cfg: DictConfig, box: Box) -> list[str]:
    """controller.u_low/u_high entries beyond the input box the surrogate was trained on (empty: none)."""
    out = []
    for key, edge, beyond in (("u_low", box.low, np.less), ("u_high", box.high, np.greater)):
        given = cfg.controller.get(key)
        if given is not None and np.any(beyond(np.asarray(list(given), dtype=np.float64), np.asarray(edge))):
            out.append(f"controller.{key}={list(given)}")
    return out


def check_input_bounds(cfg: DictConfig, box: Box) -> None:
    """Input bounds beyond the training box make the NMPC plan on extrapolated predictions: refused unless
    allow_inputs_outside_box=true, and then a loud warning."""
    outside = bounds_outside(cfg, box)
    if not outside:
        return
    what = (
        f"{' and '.join(outside)} reach beyond the surrogate's training input box "
        f"[{list(box.low)}, {list(box.high)}], where its predictions are extrapolation"
    )
    if not cfg.get("allow_inputs_outside_box", False):
        raise SettingError(f"{what}; expected bounds inside the box (or allow_inputs_outside_box=true)")
    log.warning("%s (allowed by allow_inputs_outside_box=true)", what)


def controller_box(controller: Controller) -> Box:
    """The input box the controller's model was trained on (the NMPC's surrogate)."""
    return controller.surrogate.input_box  # type: ignore[attr-defined]


def system_reference(cfg: DictConfig, system: System, tau: float) -> Reference:
    """reference.path if given, else the system's built-in reference.name, on the grid of tau (as far as max_steps
    needs it); refused when it leaves the system's joint limits, or its state box by more than the box's width."""
    box, limits = system.state_box, getattr(system, "joint_limits", None)
    steps, horizon = cfg.get("max_steps"), cfg.get("controller", {}).get("horizon")
    needed = None if steps is None or horizon is None else int(steps) + int(horizon) + 2  # + 1: a plant a period late
    ref = load_reference(
        resolve_reference_path(cfg.reference.path, cfg.system.get("paper_reference")),
        tau,
        cfg.reference.name,
        system.state_names,
        OmegaConf.to_container(cfg.system.references, resolve=True),
        (box.low[: system.nq], box.high[: system.nq]),
        None if limits is None else (limits.low, limits.high),
        system,
        needed,
    )
    far = divergence_box(system)
    beyond = far_outside(ref.x, far)
    if beyond.any():
        i, j = (int(v) for v in np.argwhere(beyond)[0])
        raise ValueError(
            f"reference {ref.name}: {system.state_names[j]} = {ref.x[i, j]:.4g} at t={ref.t[i]:.4g} s lies farther "
            f"outside the state box [{far.low[j]:g}, {far.high[j]:g}] than its width (degrees instead of radians?); "
            "expected states near the box"
        )
    return ref


def warn_jumps(ref: Reference, system: System) -> None:
    """A joint angle that jumps by more than pi in one period is no motion an arm makes: most likely an angle
    wrapped into (-pi, pi], which the arm would be driven through the long way round."""
    jump = np.abs(np.diff(ref.x[:, : system.nq], axis=0))
    if np.any(jump > np.pi):
        i, j = (int(v) for v in np.argwhere(jump > np.pi)[0])
        log.warning(
            "reference %s: %s jumps by %.3g rad between t=%.4g and %.4g s (a wrapped angle?); it is tracked as given: "
            "pass angles unwrapped (numpy.unwrap)",
            ref.name, system.state_names[j], jump[i, j], ref.t[i], ref.t[i + 1],
        )  # fmt: skip


def warn_limit_margin(ref: Reference, system: System, limits: Any) -> None:
    """A reference within the soft joint-limit margin is tracked with an offset there (the controllers keep every
    joint `margin` inside its limits): say so rather than let the offset look like a tracking error."""
    if not limits or not limits.get("margin"):
        return
    low, high, margin = np.asarray(limits["low"], float), np.asarray(limits["high"], float), float(limits["margin"])
    q = ref.x[:, : len(low)]
    inside = (q < low + margin) | (q > high - margin)
    if inside.any():
        i, j = (int(v) for v in np.argwhere(inside)[0])
        log.warning(
            "reference %s: %s = %.4g at t=%.4g s lies within %g rad of its joint limit; the controllers keep every "
            "joint that far inside its limits (controller.joint_limits.margin), so they track it with an offset there",
            ref.name, system.state_names[j], q[i, j], ref.t[i], margin,
        )  # fmt: skip


def checked_start(cfg: DictConfig, system: System) -> list[float] | None:
    """The start x0 the user set (None: the reference's), refused where no arm can start or a run would fail at once:
    checked before the controller is built (a classical Panda build compiles C first)."""
    start = None if cfg.get("x0") is None else [float(v) for v in cfg.x0]
    far = "" if start is None else diverged(np.asarray(start), divergence_box(system))
    if far:  # a run would stop there as failed at once
        raise ValueError(f"x0={start}: {far}; expected a start within the state box (or near it)")
    if start is not None and system.joint_limits is not None:  # as a reference there would be: no arm starts there
        low, high = np.asarray(system.joint_limits.low), np.asarray(system.joint_limits.high)
        q = np.asarray(start[: len(low)])
        past = np.flatnonzero((q < low) | (q > high))
        if past.size:
            j = int(past[0])
            raise ValueError(
                f"x0={start}: {system.state_names[j]} = {q[j]:g} is outside its joint limits "
                f"[{low[j]:g}, {high[j]:g}]; expected a start within the joint limits"
            )
    return start
