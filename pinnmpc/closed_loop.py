"""`python -m pinnmpc.closed_loop [overrides]`: NMPC on the surrogate tracks a reference on the RK45 plant."""

from __future__ import annotations

import logging
import math
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import hydra
import numpy as np
from omegaconf import DictConfig, OmegaConf
from tqdm.auto import tqdm

from pinnmpc.cli import StopSignal, check_choices, job_system, run_cli, say
from pinnmpc.controller.build import build_nmpc
from pinnmpc.controller.nmpc import Controller
from pinnmpc.plant.scipy_plant import PlantError, ScipyPlant
from pinnmpc.references.files import Reference, load_reference, out_of_box, resolve_reference_path
from pinnmpc.surrogate.checkpoint import load_surrogate
from pinnmpc.systems.base import Box, System
from pinnmpc.util.io import save_json, save_npz
from pinnmpc.util.settings import SettingError, validate_closed_loop

log = logging.getLogger(__name__)
SATURATED_NOTE = 0.05  # the headline notes inputs at their bounds from this share of the steps on (display only)
FINAL_SAMPLES = 10  # the last samples whose worst joint-angle error says where a run ended up


def _stats(values: np.ndarray) -> dict[str, float]:
    """Summary of a timing series in seconds."""
    if values.size == 0:
        return {"mean": float("nan"), "median": float("nan"), "p95": float("nan"), "max": float("nan")}
    return {
        "mean": float(values.mean()),
        "median": float(np.median(values)),
        "p95": float(np.percentile(values, 95)),
        "max": float(values.max()),
    }


def plant_system(system: System, cfg: DictConfig) -> System:
    """The simulated robot: the model with optional friction/mass mismatch (never seen by the controller)."""
    if cfg.friction_scale == 1.0 and cfg.mass_scale == 1.0:
        return system
    return system.with_mismatch(friction_scale=cfg.friction_scale, mass_scale=cfg.mass_scale)


def make_plant(system: System, cfg: DictConfig, tau: float) -> ScipyPlant:
    """The simulated robot of every closed loop (and of the bench's RK45 row) from the plant settings."""
    return ScipyPlant(
        plant_system(system, cfg),
        tau,
        cfg.method,
        cfg.rtol,
        cfg.atol,
        cfg.chatter_flips,
        cfg.stick_slip_tighten,
        int(cfg.max_switches),
    )


def build_controller(cfg: DictConfig, system: System) -> tuple[Controller, Box | None, float]:
    """The controller named by controller.kind, the state box its model is valid in (None: everywhere) and tau.

    kind pinn (default): NMPC on the surrogate (checkpoint, or the one shipped for this system);
    kind casadi: the classical NMPC on the true model (compiled, pinnmpc.controller.casadi_nmpc)."""
    kind = cfg.controller.get("kind", "pinn")
    if kind == "casadi":
        from pinnmpc.controller.casadi_nmpc import build_casadi_nmpc

        return build_casadi_nmpc(cfg.controller, system), None, system.tau
    if kind != "pinn":
        raise ValueError(f"controller.kind={kind!r}; expected 'pinn' or 'casadi'")
    surrogate = load_surrogate(
        cfg.checkpoint, system=system.name if cfg.checkpoint is None else None, state_names=system.state_names
    )
    check_input_bounds(cfg, surrogate.input_box)
    return build_nmpc(cfg.controller, surrogate, system), surrogate.domain, surrogate.tau


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
    log.warning("WARNING: %s (allowed by allow_inputs_outside_box=true)", what)


def simulate(
    controller: Controller,
    plant: ScipyPlant,
    ref: Reference,
    domain: Box | None = None,
    noise_sigma: float = 0.0,
    seed: int = 0,
    max_steps: int | None = None,
    progress: bool = True,
    stop: Callable[[], bool] | None = None,
    x0: Sequence[float] | None = None,
    state_box: Box | None = None,
) -> dict[str, Any]:
    """Receding-horizon loop from x0 (None: the reference's first sample); stops cleanly on a plant failure, when the
    state leaves state_box by more than its width (a diverged simulation or controller) or when stop() turns true
    (a signal), and returns what was reached."""
    horizon, nx = controller.horizon, ref.x.shape[1]
    steps = len(ref) - horizon - 1
    if steps < 1:
        raise ValueError(
            f"reference {ref.name} has {len(ref)} samples at tau; horizon {horizon} needs at least {horizon + 2}"
        )
    if max_steps is not None:
        steps = min(steps, int(max_steps))
    rng = np.random.default_rng(seed)
    lo = np.full(nx, -np.inf) if domain is None else np.array(domain.low)
    hi = np.full(nx, np.inf) if domain is None else np.array(domain.high)
    controller.reset()
    x = np.array(ref.x[0] if x0 is None else x0, dtype=np.float64)
    xs, us, status, out_of_box_steps, warned = [x], [], "ok", 0, False
    for k in tqdm(range(steps), desc="closed loop", unit="step", disable=not progress, file=sys.stderr):
        if stop is not None and stop():
            status = "interrupted"
            log.warning("interrupted after %d of %d steps; writing what was reached", k, steps)
            break
        measured = x + noise_sigma * rng.standard_normal(nx)
        if np.any(measured < lo) or np.any(measured > hi):
            out_of_box_steps += 1
            if not warned:
                log.warning(
                    "state %s at step %d is outside the surrogate's training box; predictions may be poor",
                    measured.round(3).tolist(),
                    k,
                )
                warned = True
        u = controller.make_step(measured, ref.x[k + 1 : k + 1 + horizon])
        try:
            x = plant.step(x, u)
        except PlantError as e:
            status = f"plant_failure: {e}"
            log.error("%s; stopping after %d steps", status, k)
            us.append(u)
            break
        xs.append(x)
        us.append(u)
        far = diverged(x, state_box)
        if far:
            status = f"failed: {far} after step {k}: the simulation or the controller diverged"
            log.error("%s; stopping", status)
            break
    return {
        "x": np.array(xs),
        "u": np.array(us, dtype=np.float64).reshape(-1, len(controller.low)),
        "status": status,
        "out_of_box_steps": out_of_box_steps,
    }


def metrics(
    ref: Reference,
    run: dict[str, Any],
    controller: Controller,
    plant: ScipyPlant,
    names: tuple[str, ...],
    units: tuple[str, ...] = (),
) -> dict[str, Any]:
    """metrics.json: tracking error per state (SI units), OCP and plant timings, solver statistics."""
    x = run["x"]
    err = np.abs(x - ref.x[: len(x)])
    st = controller.stats
    return {
        "reference": ref.name,
        "status": run["status"],
        "steps": len(st),
        "tau": plant.tau,
        "horizon": controller.horizon,
        **controller.describe(),
        "mae": {n: float(v) for n, v in zip(names, err.mean(0))},
        "rmse": {n: float(v) for n, v in zip(names, np.sqrt((err**2).mean(0)))},
        "max_abs_error": {n: float(v) for n, v in zip(names, err.max(0))},
        # where the run ends: the worst joint-angle error over its last FINAL_SAMPLES samples (did it follow?)
        "final_position_error_max": float(err[-FINAL_SAMPLES:, : len(names) // 2].max()) if len(err) else 0.0,
        "ocp_time_s": _stats(np.array([s.time_s for s in st])),
        "plant_step_time_s": {
            k: v for k, v in _stats(np.array(plant.step_times)).items() if k in ("mean", "median", "p95", "max")
        },
        "plant_stick_slip_steps": plant.stick_slip_steps,
        "iterations": {
            "mean": float(np.mean([s.iterations for s in st])) if st else 0.0,
            "max": max((s.iterations for s in st), default=0),
        },
        "converged_fraction": float(np.mean([s.converged for s in st])) if st else 0.0,
        "fallbacks": sum(s.fallback for s in st),
        "not_converged": sum(not s.converged for s in st),
        "out_of_box_steps": run["out_of_box_steps"],
        "u_abs_max": float(np.abs(run["u"]).max()) if len(run["u"]) else 0.0,
        "state_units": dict(zip(names, units)),  # for readers of the file (and the headline)
        "fallback_fraction": sum(s.fallback for s in st) / len(st) if st else 0.0,
    }


def divergence_box(system: System) -> Box:
    """The state box, with unbounded positions on arms whose joints turn all the way round (no joint limits)."""
    low, high = np.array(system.state_box.low, dtype=float), np.array(system.state_box.high, dtype=float)
    if system.joint_limits is None:
        low[: system.nq], high[: system.nq] = -np.inf, np.inf
    return Box(low.tolist(), high.tolist())


def diverged(x: np.ndarray, box: Box | None) -> str:
    """What is wrong with a state that is not finite or lies beyond box by more than the box's width ('' if none)."""
    if not np.all(np.isfinite(x)):
        return f"the state became non-finite ({x.tolist()})"
    if box is None:
        return ""
    beyond = np.flatnonzero(far_outside(x, box))
    if not beyond.size:
        return ""
    j, low, high = int(beyond[0]), box.low, box.high
    return f"state {j} = {x[j]:.3g}, beyond the state box [{low[j]:.3g}, {high[j]:.3g}] by more than its width"


def far_outside(x: np.ndarray, box: Box) -> np.ndarray:
    """Which entries of states x (..., n) lie beyond the box by more than its width: no arm of the system goes there."""
    low, high = np.asarray(box.low, dtype=float), np.asarray(box.high, dtype=float)
    return (x < low - (high - low)) | (x > high + (high - low))


def limits_and_saturation(run: dict[str, Any], controller: Controller, system: System) -> dict[str, Any]:
    """What a tracking error alone does not say: samples past the arm's joint limits (and how far), and the share of
    steps with an input at its bound (a reference asking more than the arm can give)."""
    q, u = run["x"][:, : system.nq], run["u"]
    excess = np.zeros(len(q))
    if system.joint_limits is not None:
        low, high = np.asarray(system.joint_limits.low), np.asarray(system.joint_limits.high)
        excess = np.maximum(q - high, low - q).max(axis=1).clip(min=0.0)
    low_u, high_u = np.asarray(controller.low, dtype=float), np.asarray(controller.high, dtype=float)
    span = high_u - low_u
    tol = 1e-9 * np.where(np.isfinite(span), span, 0.0)
    at_bound = (u <= low_u + tol) | (u >= high_u - tol)
    return {
        "joint_limit_samples": int((excess > 0).sum()),  # samples with a joint past its limit (system.joint_limits)
        "joint_limit_excess_max": float(excess.max(initial=0.0)),  # rad
        "saturated_fraction": float(at_bound.any(axis=1).mean()) if len(u) else 0.0,  # steps with an input at a bound
    }


def verdict(m: dict[str, Any], max_fallback_fraction: float) -> str:
    """The run's status: a run that mostly applied fallback inputs did not control anything, whatever it tracked."""
    if m["status"] != "ok" or not m["steps"]:
        return m["status"]
    n, k = m["steps"], m["fallbacks"]
    if k == n:
        return f"failed: every one of the {n} steps fell back (no OCP solve succeeded; inputs were not the NMPC's)"
    if k / n > max_fallback_fraction:
        limit = f"failure.max_fallback_fraction={max_fallback_fraction:g}"
        return f"failed: {k} of {n} steps fell back ({k / n:.0%} > {limit})"
    return "ok"


def system_reference(cfg: DictConfig, system: System, tau: float) -> Reference:
    """reference.path if given, else the system's built-in reference.name, on the grid of tau (as far as max_steps
    needs it); refused when it leaves the system's joint limits, or its state box by more than the box's width."""
    box, limits = system.state_box, getattr(system, "joint_limits", None)
    steps, horizon = cfg.get("max_steps"), cfg.get("controller", {}).get("horizon")
    needed = None if steps is None or horizon is None else int(steps) + int(horizon) + 1
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


def run_closed_loop(cfg: DictConfig, run_dir: Path, stop: StopSignal | None = None) -> dict[str, Any]:
    """Check the settings, load controller and reference, run the loop (until the end, a plant failure or a signal
    to stop), write metrics.json, trajectory.npz and plots."""
    system: System = job_system(cfg, validate_closed_loop)
    start = checked_start(cfg, system)
    controller, domain, tau = build_controller(cfg, system)
    differs = arm_differences(getattr(getattr(controller, "surrogate", None), "meta", None), cfg)
    if differs:  # before the run: a network of another arm tracks whatever it tracks
        log.warning(
            "WARNING: the network was trained for another description of this arm (system.dynamics %s differ): "
            "it predicts a different arm from the one the plant simulates",
            ", ".join(differs),
        )
    if cfg.tau is not None and abs(cfg.tau - tau) > 1e-12:
        raise ValueError(
            f"tau={cfg.tau} differs from the controller model's tau={tau} (a PINN predicts one period of its tau)"
        )
    ref = system_reference(cfg, system, tau)
    warn_jumps(ref, system)
    warn_limit_margin(ref, system, cfg.controller.get("joint_limits"))
    box = domain if domain is not None else system.state_box
    dist = out_of_box(ref, box.low, box.high)
    if dist > 0:
        what = "the surrogate's training box" if domain is not None else "the system's state box"
        log.warning("reference leaves %s by up to %.3g; tracking there is extrapolation", what, dist)
    plant = make_plant(system, cfg.plant, tau)
    requested = None if stop is None else (lambda: stop.requested)
    run = simulate(
        controller,
        plant,
        ref,
        domain,
        cfg.noise_sigma,
        cfg.seed,
        cfg.max_steps,
        cfg.progress,
        requested,
        start,
        divergence_box(system),
    )
    result = metrics(ref, run, controller, plant, system.state_names, system.state_units)
    failure = cfg.get("failure") or {}
    result.update(limits_and_saturation(run, controller, system))
    result["status"] = verdict(result, float(failure.get("max_fallback_fraction", 1.0)))
    result["input_bounds_outside_box"] = bool(domain is not None and bounds_outside(cfg, controller_box(controller)))
    result["plant_mismatch"] = {
        "friction_scale": float(cfg.plant.friction_scale),
        "mass_scale": float(cfg.plant.mass_scale),
    }
    # the headline says "did not follow" past this final error (the robustness grid's bound of a bounded run)
    result["tracking_bound"] = float(cfg.system.get("robustness", {}).get("bound", math.inf))
    # how far a user's start x0 lies off the reference's first state (0: it starts on it)
    result["start_off_reference"] = 0.0 if start is None else float(np.abs(np.asarray(start) - ref.x[0]).max())
    result["network_arm_differs"] = differs  # system.dynamics keys
    st = controller.stats
    n = len(run["x"])
    save_npz(
        run_dir / "trajectory.npz",
        t=ref.t[:n],
        x=run["x"],
        x_ref=ref.x[:n],
        u=run["u"],
        ocp_time_s=np.array([s.time_s for s in st]),
        iterations=np.array([s.iterations for s in st]),
        cost=np.array([s.cost for s in st]),
        converged=np.array([s.converged for s in st]),
        fallback=np.array([s.fallback for s in st]),
    )
    save_json(run_dir / "metrics.json", result)
    if cfg.plots and len(run["u"]):
        write_plots(cfg, system, ref, run, controller, run_dir)
    return result


def controller_box(controller: Controller) -> Box:
    """The input box the controller's model was trained on (the NMPC's surrogate)."""
    return controller.surrogate.input_box  # type: ignore[attr-defined]


def write_plots(
    cfg: DictConfig, system: System, ref: Reference, run: dict[str, Any], controller: Controller, run_dir: Path
) -> None:
    """closed_loop.png, and with animate=true closed_loop.gif of the arm (stick drawing from its kinematics)."""
    from pinnmpc.util import plots

    n = len(run["x"])
    title = f"{system.name}: closed loop on {ref.name} ({controller.describe()['solver']})"
    labels = plots.Labels.of(system)
    low, high = np.asarray(controller.low).tolist(), np.asarray(controller.high).tolist()
    fig = plots.tracking_figure(ref.t[:n], ref.x[:n], run["x"], run["u"], low, high, labels, title=title)
    plots.save_figure(fig, run_dir / "closed_loop.png")
    if cfg.animate:
        nq = system.nq
        error = np.abs(run["x"][:, :nq] - ref.x[:n, :nq]).max(axis=1)
        points_ref, points = system.kinematics(ref.x[:n, :nq]), system.kinematics(run["x"][:, :nq])
        gif_title = f"{system.name} on {ref.name}"
        plots.animate_arm(
            ref.t[:n],
            points_ref,
            points,
            run_dir / "closed_loop.gif",
            title=gif_title,
            error=error,
            progress=cfg.progress,
        )


def headline(m: dict[str, Any], run_dir: Path) -> str:
    """One line from metrics.json: status, tracking of every joint angle, OCP vs plant time, what went wrong."""
    names = list(m["mae"])
    units = m.get("state_units", {})
    mae = ", ".join(f"{n} {m['mae'][n]:.2e} {units.get(n, '')}".rstrip() for n in names[: len(names) // 2])
    real_time = bool(m.get("real_time"))  # a real-time iteration stops after its step(s) by design: not news
    trouble = [
        f"{m[k]} {label}"
        for k, label in (
            ("fallbacks", "fallbacks"),
            ("not_converged", "not converged"),
            ("out_of_box_steps", "out of box"),
        )
        if m[k] and not (real_time and k == "not_converged")
    ] + (["input bounds beyond the training box"] if m.get("input_bounds_outside_box") else [])
    if m.get("final_position_error_max", 0.0) > m.get("tracking_bound", math.inf):
        trouble.append(f"did not follow: it ends {m['final_position_error_max']:.2g} rad off the reference")
    if m.get("joint_limit_samples"):
        past = f"{m['joint_limit_samples']} samples past a joint limit"
        trouble.append(f"{past} (by up to {m['joint_limit_excess_max']:.1e} rad)")
    if m.get("saturated_fraction", 0.0) >= SATURATED_NOTE:
        off = {k: v for k, v in (m.get("plant_mismatch") or {}).items() if v != 1.0}
        why = f"the plant differs from the model: {', '.join(f'{k} {v:g}' for k, v in off.items())}" if off else ""
        if not why and m.get("start_off_reference", 0.0) > 0.0:
            why = "it starts off the reference, x0"
        why = why or "the reference may ask too much"
        trouble.append(f"inputs at a bound in {m['saturated_fraction']:.0%} of steps ({why})")
    return (
        f"{m['status']}: {m['steps']} steps on {m['reference']} with {m['solver']}"
        + (" as a real-time iteration" if real_time else "")
        + (f" (offset-free, gain {m['disturbance_gain']:g})" if m["disturbance_gain"] > 0 else "")
        + f"; MAE {mae}; OCP median {1e3 * m['ocp_time_s']['median']:.2f} ms "
        f"(plant step {1e3 * m['plant_step_time_s']['median']:.2f} ms)"
        + (f"; {', '.join(trouble)}" if trouble else "")
        + f"; outputs in {run_dir}"
    )


@hydra.main(version_base="1.3", config_path="../conf", config_name="closed_loop")
def main(cfg: DictConfig) -> None:
    """CLI: print the headline numbers and where the outputs went."""
    run_dir = Path(hydra.core.hydra_config.HydraConfig.get().runtime.output_dir)
    with StopSignal() as stop:
        m = run_cli(lambda: run_closed_loop(cfg, run_dir, stop), "pinnmpc.closed_loop", run_dir)
    say(headline(m, run_dir), run_dir, "pinnmpc.closed_loop")
    if m["status"] == "interrupted":
        print(f"pinnmpc.closed_loop: interrupted by {stop.name} after {m['steps']} steps", file=sys.stderr)
        sys.exit(stop.exit_code)
    if m["status"] != "ok":
        sys.exit(1)


if __name__ == "__main__":
    check_choices("pinnmpc.closed_loop")
    main()
