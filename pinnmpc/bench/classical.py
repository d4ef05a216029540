"""Section 6: the PINN controller against the classical NMPC on the true model (CasADi, compiled), in the same
process, on the same reference, plant and protocol: one table per system."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from pinnmpc.bench.common import controller_cfg, make_plant
from pinnmpc.bench.loops import loop_row, run_controller
from pinnmpc.bench.paired import paired_ocp
from pinnmpc.controller.build import build_nmpc
from pinnmpc.controller.settings import GAUSS_NEWTON
from pinnmpc.references.files import Reference
from pinnmpc.surrogate.checkpoint import Surrogate
from pinnmpc.systems.base import System

log = logging.getLogger(__name__)

CASADI_CONFIG = "conf/controller/casadi.yaml"  # where the classical controller's settings come from


def classical_cfg(cfg: DictConfig, solver: str, keys: Sequence[str] | None = None) -> DictConfig:
    """The classical controller's config with `solver`, and the settings listed in keys (null: classical.shared:
    horizon, weights, bounds, offset-free estimator) taken from the PINN controller, so both solve the same problem."""
    keys = cfg.classical.shared if keys is None else keys
    shared = {k: cfg.controller[k] for k in keys if k in cfg.controller}
    return OmegaConf.merge(cfg.classical.controller, shared, {"solver": solver})


def classical_solvers(cfg: DictConfig) -> list[str]:
    """The classical rows: the casadi config's default solver first, then classical.solvers."""
    default = str(cfg.classical.controller.solver)
    return [default, *(str(s) for s in cfg.classical.solvers if str(s) != default)]


def classical_variants(cfg: DictConfig, rti: bool) -> list[tuple[str, DictConfig]]:
    """The classical rows: the arm's default (its strongest setting: a real-time iteration where it tracks as the
    converged solve), with classical.rti its other mode, today's RK4 shooting where the default transcribes
    otherwise, and classical.solvers (converged: a real-time iteration needs sqpmethod)."""
    first, *others = classical_solvers(cfg)
    default = classical_cfg(cfg, first)
    variants = [(first, default)]
    if rti and default.solver == "sqpmethod":
        fast = bool(default.get("rti", False))
        variants.append((f"{first}_converged" if fast else f"{first}_rti", OmegaConf.merge(default, {"rti": not fast})))
    if default.get("transcription", "rk4") != "rk4":
        shooting = {"transcription": "rk4", "qpsol": "qrqp", "rti": False}
        variants.append((f"{first}_rk4", OmegaConf.merge(default, shooting)))
    variants += [(name, OmegaConf.merge(classical_cfg(cfg, name), {"rti": False})) for name in others]
    return variants


def available(cfg: DictConfig) -> bool:
    """Whether the classical controller's config was composed into the bench config."""
    return cfg.classical.get("controller") is not None


def mismatch_rows(
    cfg: DictConfig, system: System, surrogate: Surrogate, ref: Reference, scale: float
) -> dict[str, dict[str, Any]]:
    """Both controllers on a plant whose friction is scaled: neither model is exact there, so the classical NMPC
    gets the PINN controller's offset-free estimator too (its best setting under mismatch)."""
    from pinnmpc.controller.classical.nmpc import build_casadi_nmpc

    if not 0 < scale < float("inf"):
        raise ValueError(f"classical.friction_scales holds {scale}; expected positive numbers")
    off = OmegaConf.merge(cfg, {"plant": {"friction_scale": scale}})
    solver, tag = str(cfg.controller.solver), f"plant friction x{scale:g}"
    pinn, _ = run_controller(off, system, surrogate, ref, solver, record=False)
    estimating = {"disturbance": cfg.controller.disturbance}
    classical = OmegaConf.merge(classical_cfg(cfg, classical_solvers(cfg)[0]), estimating)
    row = loop_row(off, system, build_casadi_nmpc(classical, system), None, system.tau, ref)
    log.info("classical: %s, both controllers done", tag)
    pinn.update(label=f"PINN-MPC, {solver}, {tag}", model="pinn", plant_friction_scale=scale)
    row.update(label=f"classical NMPC, {row['solver']}, {tag}", model="classical", plant_friction_scale=scale)
    return {f"pinn_{solver}_friction_{scale:g}": pinn, f"classical_friction_{scale:g}": row}


EXACT = "exact values (true model's values, PINN's Jacobians)"  # label of controller.model=exact_values rows
PRIOR = "physics prior alone (no network)"  # label of controller.model=prior rows


def pinn_variants(
    cfg: DictConfig, solver: str, rti: bool, fast: bool, prior: bool = False
) -> list[tuple[str, str, dict[str, Any]]]:
    """The PINN rows beside the configured controller (fast: whether it runs as a real-time iteration), as (key
    suffix, label tail, controller changes): its other mode, converged or real-time (classical.rti), the true
    model's values, converged and as a real-time iteration (classical.exact_values) with the system's steps per
    sample, as controller=exact runs it, and for a network with a physics prior (prior) that prior alone in the
    configured mode (classical.prior_alone)."""
    lifted = solver == "lifted_gauss_newton"
    out = []
    if rti and lifted:
        other = ("_converged", ", converged") if fast else ("_rti", ", real-time iteration")
        out.append((*other, {"rti": not fast}))
    if cfg.classical.get("exact_values", False):
        for real_time in (False, True) if rti and lifted else (False,):
            suffix, tail = (
                ("_exact_values_rti", f", {EXACT}, real-time iteration")
                if real_time
                else ("_exact_values", f", {EXACT}")
            )
            steps = {"rti_steps": int(cfg.system.control.get("rti_steps", 1))} if real_time else {}
            out.append((suffix, tail, {"model": "exact_values", "rti": real_time, "solvers": {solver: steps}}))
    if prior and solver in GAUSS_NEWTON and cfg.classical.get("prior_alone", False):
        out.append(("_prior", f", {PRIOR}", {"model": "prior"}))
    return out


def classical_plot(cl: dict[str, Any], system: System, path: Path) -> Path:
    """classical.png: every row of section 6 as (OCP median, worst joint-angle MAE), log-log."""
    from pinnmpc.util import plots

    angles = list(system.state_names[: system.nq])
    points = {
        r["label"]: (r["ocp_time_s"]["median"], max(r["mae"][n] for n in angles))
        for r in cl["rows"].values()
        if "plant_friction_scale" not in r  # the exact plant only: mismatch rows answer another question
    }
    title = f"{system.name}, {cl['reference']}: tracking against OCP time (exact plant)"
    fig = plots.frontier_figure(points, "OCP median [s]", "worst joint-angle MAE [rad]", title)
    return plots.save_figure(fig, path)


def bench_classical(
    cfg: DictConfig,
    system: System,
    surrogate: Surrogate,
    ref: Reference,
    pinn_rows: dict[str, dict[str, Any]] | None = None,
) -> dict[str, Any]:
    """The PINN controller (controller.solver) and each classical solver, one closed loop each on the same
    reference and plant; a PINN row that section 2 already ran is reused (same process, same protocol)."""
    if not available(cfg):
        raise ValueError(f"classical.enabled=true needs the classical controller's config {CASADI_CONFIG}")
    from pinnmpc.controller.classical.nmpc import build_casadi_nmpc

    if abs(system.tau - surrogate.tau) > 1e-12:
        raise ValueError(f"the system's tau {system.tau} differs from the surrogate's {surrogate.tau}")
    solver = str(cfg.controller.solver)
    pinn = (pinn_rows or {}).get(f"pinn_{solver}")
    if pinn is None:
        pinn, _ = run_controller(cfg, system, surrogate, ref, solver, record=False)
        log.info("classical: PINN %s done in %.1f s", solver, pinn["wall_s"])
    fast = bool(pinn.get("real_time"))  # the configured controller's mode (rti=null: decided by its network)
    tag = ", real-time iteration" if fast else ""
    rows = {f"pinn_{solver}": {**pinn, "label": f"PINN-MPC, {solver}{tag}", "model": "pinn"}}
    rti = bool(cfg.classical.get("rti", False))
    prior = getattr(surrogate.model, "prior", None) is not None
    for suffix, tail, changes in pinn_variants(cfg, solver, rti, fast, prior):  # e.g. both at their cheapest too
        row, _ = run_controller(cfg, system, surrogate, ref, solver, record=False, **changes)
        rows[f"pinn_{solver}{suffix}"] = {**row, "label": f"PINN-MPC, {solver}{tail}", "model": "pinn"}
        log.info("classical: PINN %s%s done in %.1f s", solver, tail, row["wall_s"])
    variants = classical_variants(cfg, rti)
    for name, settings in variants:
        controller = build_casadi_nmpc(settings, system)  # compiled here, outside the timed loop
        row = loop_row(cfg, system, controller, None, system.tau, ref)
        label = f"classical NMPC, {row['solver']}"  # the table adds the mode (offset-free where the arm runs it)
        rows[f"classical_{name}"] = {**row, "label": label, "model": "classical"}
        log.info("classical: %s done in %.1f s", row["solver"], row["wall_s"])
    for scale in (float(f) for f in cfg.classical.friction_scales):
        rows.update(mismatch_rows(cfg, system, surrogate, ref, scale))
    paired = None
    if cfg.classical.get("paired", False):  # loops one after the other see the machine's drift; interleaved ones not
        ours = build_nmpc(controller_cfg(cfg), surrogate, system)
        default = rows[f"classical_{variants[0][0]}"]["solver"]  # e.g. casadi-sqpmethod-rti
        controllers = {f"pinn_{solver}": ours, default: build_casadi_nmpc(variants[0][1], system)}
        plant = lambda: make_plant(cfg, system, surrogate.tau)  # noqa: E731
        paired = paired_ocp(controllers, plant, ref, cfg.closed_loop.max_steps, system.nq)
    return {
        "reference": ref.name,
        "horizon": int(cfg.controller.horizon),
        "shared": [str(k) for k in cfg.classical.shared],
        "rows": rows,
        "paired": paired,
    }
