"""What a closed loop is judged by: metrics.json, its verdict and the one-line headline."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from pinnmpc.controller.base import Controller
from pinnmpc.plant.base import Plant
from pinnmpc.references.data import Reference
from pinnmpc.simulation.fault_setup import Recovery
from pinnmpc.simulation.faults import fault_report, position_error
from pinnmpc.simulation.loop import LoopResult
from pinnmpc.simulation.model_fit import fit_note
from pinnmpc.systems.base import System

SATURATED_NOTE = 0.05  # the headline notes inputs at their bounds from this share of the steps on (display only)
REVERSAL_STEP = 0.01  # an input step counts towards reversals from this share of its box width on (not noise)
REVERSAL_NOTE = 0.2  # the headline notes chattering inputs from this share of reversing steps on (display only)
FINAL_SAMPLES = 10  # the last samples whose worst joint-angle error says where a run ended up


def _stats(values: np.ndarray) -> dict[str, float]:
    """Summary of a timing series in seconds."""
    if values.size == 0:
        return {k: float("nan") for k in ("mean", "median", "p95", "p99", "max")}
    return {
        "mean": float(values.mean()),
        "median": float(np.median(values)),
        "p95": float(np.percentile(values, 95)),
        "p99": float(np.percentile(values, 99)),
        "max": float(values.max()),
    }


def metrics(
    ref: Reference,
    run: LoopResult,
    controller: Controller,
    plant: Plant,
    names: tuple[str, ...],
    units: tuple[str, ...] = (),
) -> dict[str, Any]:
    """metrics.json: tracking error per state (SI units), OCP and plant timings, solver statistics."""
    x = run.x
    err = np.abs(x - ref.x[: len(x)])
    st = controller.stats
    described = controller.describe()
    return {
        "reference": ref.name,
        "status": run.status,
        "steps": len(st),
        "tau": plant.tau,
        "horizon": controller.horizon,
        **described,
        "mae": {n: float(v) for n, v in zip(names, err.mean(0))},
        "rmse": {n: float(v) for n, v in zip(names, np.sqrt((err**2).mean(0)))},
        "max_abs_error": {n: float(v) for n, v in zip(names, err.max(0))},
        # where the run ends: the worst joint-angle error over its last FINAL_SAMPLES samples (did it follow?)
        "final_position_error_max": float(err[-FINAL_SAMPLES:, : len(names) // 2].max()) if len(err) else 0.0,
        "ocp_time_s": _stats(np.array([s.time_s for s in st])),
        # solves that took longer than the control period: on this machine the controller was not real-time there
        "over_period": sum(s.time_s > plant.tau for s in st),
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
        # a real-time loop's samples solved to convergence (the first, and steps beyond rti_trust or at joint limits)
        "solved_fully": _solved_fully(st, described),
        "out_of_box_steps": run.out_of_box_steps,
        "u_abs_max": float(np.abs(run.u).max()) if len(run.u) else 0.0,
        "state_units": dict(zip(names, units)),  # for readers of the file (and the headline)
        "fallback_fraction": sum(s.fallback for s in st) / len(st) if st else 0.0,
        "model_monitor": model_monitor(run, names),  # the model's one-step miss on the measured states
        "measurement_guard": None if run.guard is None else run.guard.report(),  # readings rejected, inputs held
    }


def faults_metrics(run: LoopResult, ref: Reference, nq: int, tau: float, recovery: Recovery) -> list[dict[str, Any]]:
    """metrics.json's `faults`: each injected fault, what was done and the samples tracking took to recover."""
    if not run.faults or run.guard is None:
        return []
    error = position_error(run.x, ref.x, nq)
    r = recovery
    return fault_report(run.faults, run.guard, error, tau, r.window, r.factor, r.tolerance, r.samples)


def faults_note(m: dict[str, Any]) -> str:
    """The headline's faults: each by name, what was done, and its recovery."""
    parts = []
    for f in m.get("faults") or []:
        n = f.get("recovery_samples")
        rec = "not recovered" if n is None else f"recovered in {n} samples"
        if f.get("recovered") is None:
            rec = "no recovery to measure"
        if n is not None and not f.get("recovered"):
            rec += f" (more than {f['recovery_bound']})"
        parts.append(f"{f['fault']} ({f['what']}, t={f['t']:.3g} s): {'; '.join(f['actions'])}; {rec}")
    if not parts:  # no fault injected: whatever the guard had to do came from the run itself
        g = m.get("measurement_guard") or {}
        counts = ("rejected_nonfinite", "rejected_jump", "inputs_held")
        parts = [f"{g[k]} {k.replace('_', ' ')}" for k in counts if g.get(k)]
    return f"; faults: {' | '.join(parts)}" if parts else ""


def model_monitor(run: LoopResult, names: tuple[str, ...]) -> dict[str, Any] | None:
    """How far the controller's model misses the measured next state (median and p95 of |error| per state, SI
    units): the figure that says the model no longer matches the robot (None: the controller has no model step)."""
    e = run.prediction_error
    if e is None or not len(e):
        return None
    a = np.abs(e)
    return {
        "median": {n: float(v) for n, v in zip(names, np.median(a, axis=0))},
        "p95": {n: float(v) for n, v in zip(names, np.percentile(a, 95, axis=0))},
        "samples": len(e),
    }


def limits_and_saturation(run: LoopResult, controller: Controller, system: System) -> dict[str, Any]:
    """What a tracking error alone does not say: samples past the arm's joint limits (and how far), and the share of
    steps with an input at its bound (a reference asking more than the arm can give)."""
    q, u = run.x[:, : system.nq], run.u
    excess = np.zeros(len(q))
    if system.joint_limits is not None:
        low, high = np.asarray(system.joint_limits.low), np.asarray(system.joint_limits.high)
        excess = np.maximum(q - high, low - q).max(axis=1).clip(min=0.0)
    low_u, high_u = np.asarray(controller.low, dtype=float), np.asarray(controller.high, dtype=float)
    span = high_u - low_u
    tol = 1e-9 * np.where(np.isfinite(span), span, 0.0)
    at_bound = (u <= low_u + tol) | (u >= high_u - tol)
    steps = np.diff(u, axis=0)
    big = np.abs(steps) > REVERSAL_STEP * np.where(np.isfinite(span), span, np.inf)
    reversed_ = (steps[1:] * steps[:-1] < 0) & big[1:] & big[:-1]  # a step undoing the one before: chatter
    return {
        # per input, the share of samples whose input step reverses the previous one (both beyond 1% of its box)
        "input_reversals": {
            n: float(r)
            for n, r in zip(system.input_names, reversed_.mean(axis=0) if len(reversed_) else np.zeros(u.shape[-1]))
        },
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


def monitor_note(m: dict[str, Any]) -> str:
    """The headline's model monitor: the worst joint angle's p95 one-step miss of the model on the robot, and
    whether the model fits the robot at all (model_fit)."""
    mon = m.get("model_monitor")
    if not mon:
        return ""
    names = list(mon["p95"])[: len(mon["p95"]) // 2]
    worst = max(names, key=lambda n: mon["p95"][n])
    unit = (m.get("state_units") or {}).get(worst, "")
    return f"; model one-step miss p95 {mon['p95'][worst]:.1e} {unit} ({worst})".replace("  ", " ") + fit_note(m)


def estimator_note(m: dict[str, Any]) -> str:
    """The headline's offset-free estimator: its gain, and the notch where it is on (nothing when off)."""
    if not m["disturbance_gain"] > 0:
        return ""
    return f" (offset-free, gain {m['disturbance_gain']:g}{', notch' if m.get('disturbance_notch') else ''})"


def _solved_fully(stats: list[Any], described: dict[str, Any]) -> int | None:
    """Samples of a PINN real-time loop that took more than its steps or converged: solved fully (None: not such a
    loop)."""
    if not described.get("real_time") or "rti_trust" not in described:
        return None
    steps = described.get("rti_steps") or 1
    return sum(1 for s in stats if s.converged or s.iterations != steps)


def real_time_note(m: dict[str, Any]) -> str:
    """' as a real-time iteration', with its trust bound and how many samples it solved fully where it has one."""
    if not m.get("real_time"):
        return ""
    trust = m.get("rti_trust")
    if trust is None or not math.isfinite(trust) or m.get("solved_fully") is None:
        return " as a real-time iteration"
    return f" as a real-time iteration (trust {trust:g}: {m['solved_fully']} of {m['steps']} samples solved fully)"


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
    followed = m.get("final_position_error_max", 0.0) <= m.get("tracking_bound", math.inf)
    if not m.get("followed", followed):  # metrics.json's `followed`
        trouble.append(f"did not follow: it ends {m['final_position_error_max']:.2g} rad off the reference")
    if m.get("over_period"):
        trouble.append(f"{m['over_period']} solves longer than the control period ({1e3 * m['tau']:g} ms)")
    trouble += franka_trouble(m.get("franka"))
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
    reversals = m.get("input_reversals") or {}
    worst = max(reversals, key=reversals.get, default=None)
    if worst is not None and reversals[worst] >= REVERSAL_NOTE:
        tune = ""
        if m["disturbance_gain"]:
            tune = (
                "a lower controller.disturbance.gain"
                if m.get("disturbance_notch")
                else ("controller.disturbance.notch=true or a lower gain")
            )
        trouble.append(
            f"{worst} reverses its last step in {reversals[worst]:.0%} of samples (chatter"
            + (f": try {tune})" if tune else ")")
        )
    return (
        f"{m['status']}: {m['steps']} steps on {m['reference']} with {m['solver']}"
        + real_time_note(m)
        + estimator_note(m)
        + f"; MAE {mae}; OCP median {1e3 * m['ocp_time_s']['median']:.2f} ms, p99 "
        f"{1e3 * m['ocp_time_s'].get('p99', math.nan):.2f} ms "
        f"(plant step {1e3 * m['plant_step_time_s']['median']:.2f} ms)"
        + monitor_note(m)
        + faults_note(m)
        + (f"; {', '.join(trouble)}" if trouble else "")
        + f"; outputs in {run_dir}"
    )


def robot_outcome(plant: Any, status: str) -> tuple[dict[str, Any], str]:
    """A robot plant closed (the arm stopped, at rest or not) and its report, and the run's status failed by its
    first libfranka error; ({}, status) for a simulated plant."""
    if not hasattr(plant, "report"):
        return {}, status
    plant.close()
    report = plant.report()
    if report["errors"] and status == "ok":
        status = f"failed: libfranka: {report['errors'][0]}"
    return {"franka": report}, status


def franka_trouble(report: dict[str, Any] | None) -> list[str]:
    """What a robot run's headline says of the robot: libfranka's errors, the safety layer's actions, the end."""
    if not report:
        return []
    safety = report.get("safety", {})
    said = [f"{len(report['errors'])} libfranka errors ({report['errors'][0]})"] if report.get("errors") else []
    said += [f"{v} {k.replace('_', ' ')}" for k, v in safety.items() if v]
    said += [f"{report['late_commands']} commands sent late"] if report.get("late_commands") else []  # past the period
    #   or past plant.command_at by more than two ticks: a dead time that was not the model's
    return said + ([] if report.get("at_rest") else ["the arm was not at rest at the end"])
