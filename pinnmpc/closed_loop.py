"""`python -m pinnmpc.closed_loop [overrides]`: NMPC on the surrogate tracks a reference on the RK45 plant."""

from __future__ import annotations

import dataclasses
import logging
import sys
from pathlib import Path
from typing import Any

import hydra
import numpy as np
from hydra.utils import instantiate
from omegaconf import DictConfig
from tqdm.auto import tqdm

from pinnmpc.cli import run_cli
from pinnmpc.controller.build import build_nmpc
from pinnmpc.controller.nmpc import NMPC
from pinnmpc.io import save_json, save_npz
from pinnmpc.plant import PlantError, ScipyPlant
from pinnmpc.references import Reference, load_reference, out_of_box, resolve_reference_path
from pinnmpc.surrogate import load_surrogate
from pinnmpc.systems.base import System
from pinnmpc.threads import use_threads

log = logging.getLogger(__name__)


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
    params = getattr(system, "params", None)
    if params is None or (cfg.friction_scale == 1.0 and cfg.mass_scale == 1.0):
        return system
    new = dataclasses.replace(params, friction_scale=cfg.friction_scale, mass_scale=cfg.mass_scale)
    return dataclasses.replace(system, params=new)


def simulate(
    nmpc: NMPC,
    plant: ScipyPlant,
    ref: Reference,
    noise_sigma: float = 0.0,
    seed: int = 0,
    max_steps: int | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Receding-horizon loop; stops cleanly on a plant failure and returns what was reached."""
    horizon, nx = nmpc.horizon, ref.x.shape[1]
    steps = len(ref) - horizon - 1
    if steps < 1:
        raise ValueError(
            f"reference {ref.name} has {len(ref)} samples at tau; horizon {horizon} needs at least {horizon + 2}"
        )
    if max_steps is not None:
        steps = min(steps, int(max_steps))
    rng = np.random.default_rng(seed)
    box = nmpc.surrogate.domain
    lo, hi = np.array(box.low), np.array(box.high)
    nmpc.reset()
    x = np.array(ref.x[0], dtype=np.float64)
    xs, us, status, out_of_box_steps, warned = [x], [], "ok", 0, False
    for k in tqdm(range(steps), desc="closed loop", unit="step", disable=not progress, file=sys.stderr):
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
        u = nmpc.make_step(measured, ref.x[k + 1 : k + 1 + horizon])
        try:
            x = plant.step(x, u)
        except PlantError as e:
            status = f"plant_failure: {e}"
            log.error("%s; stopping after %d steps", status, k)
            us.append(u)
            break
        xs.append(x)
        us.append(u)
    return {
        "x": np.array(xs),
        "u": np.array(us, dtype=np.float64).reshape(-1, nmpc.ocp.nu),
        "status": status,
        "out_of_box_steps": out_of_box_steps,
    }


def metrics(
    ref: Reference, run: dict[str, Any], nmpc: NMPC, plant: ScipyPlant, names: tuple[str, ...]
) -> dict[str, Any]:
    """metrics.json: tracking error per state (SI units), OCP and plant timings, solver statistics."""
    x = run["x"]
    err = np.abs(x - ref.x[: len(x)])
    st = nmpc.stats
    return {
        "reference": ref.name,
        "status": run["status"],
        "steps": len(st),
        "tau": plant.tau,
        "horizon": nmpc.horizon,
        "solver": type(nmpc.solver).__name__,
        "disturbance_gain": float(nmpc.disturbance_gain),
        "mae": {n: float(v) for n, v in zip(names, err.mean(0))},
        "rmse": {n: float(v) for n, v in zip(names, np.sqrt((err**2).mean(0)))},
        "max_abs_error": {n: float(v) for n, v in zip(names, err.max(0))},
        "ocp_time_s": _stats(np.array([s.time_s for s in st])),
        "plant_step_time_s": {
            k: v for k, v in _stats(np.array(plant.step_times)).items() if k in ("mean", "median", "p95")
        },
        "iterations": {
            "mean": float(np.mean([s.iterations for s in st])) if st else 0.0,
            "max": max((s.iterations for s in st), default=0),
        },
        "converged_fraction": float(np.mean([s.converged for s in st])) if st else 0.0,
        "fallbacks": sum(s.fallback for s in st),
        "out_of_box_steps": run["out_of_box_steps"],
        "u_abs_max": float(np.abs(run["u"]).max()) if len(run["u"]) else 0.0,
    }


def run_closed_loop(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Load surrogate and reference, run the loop, write metrics.json, trajectory.npz and plots."""
    use_threads(cfg.threads)
    system: System = instantiate(cfg.system)
    surrogate = load_surrogate(cfg.checkpoint, nx=len(system.state_names), nu=len(system.input_names))
    if cfg.tau is not None and abs(cfg.tau - surrogate.tau) > 1e-12:
        raise ValueError(
            f"tau={cfg.tau} differs from the surrogate's tau={surrogate.tau} (a PINN predicts one period of its tau)"
        )
    ref = load_reference(resolve_reference_path(cfg.reference.path), surrogate.tau, cfg.reference.name)
    dist = out_of_box(ref, surrogate.domain.low, surrogate.domain.high)
    if dist > 0:
        log.warning(
            "reference leaves the surrogate's training box by up to %.3g; tracking there is extrapolation", dist
        )
    nmpc = build_nmpc(cfg.controller, surrogate)
    plant = ScipyPlant(plant_system(system, cfg.plant), surrogate.tau, cfg.plant.method, cfg.plant.rtol, cfg.plant.atol)
    run = simulate(nmpc, plant, ref, cfg.noise_sigma, cfg.seed, cfg.max_steps, cfg.progress)
    result = metrics(ref, run, nmpc, plant, system.state_names)
    n = len(run["x"])
    save_npz(
        run_dir / "trajectory.npz",
        t=ref.t[:n],
        x=run["x"],
        x_ref=ref.x[:n],
        u=run["u"],
        ocp_time_s=np.array([s.time_s for s in nmpc.stats]),
        iterations=np.array([s.iterations for s in nmpc.stats]),
        cost=np.array([s.cost for s in nmpc.stats]),
        converged=np.array([s.converged for s in nmpc.stats]),
        fallback=np.array([s.fallback for s in nmpc.stats]),
    )
    save_json(run_dir / "metrics.json", result)
    if cfg.plots:
        from pinnmpc import plots

        fig = plots.tracking_figure(
            ref.t[:n],
            ref.x[:n],
            run["x"],
            run["u"],
            nmpc.low.tolist(),
            nmpc.high.tolist(),
            title=f"closed loop on {ref.name}",
        )
        plots.save_figure(fig, run_dir / "closed_loop.png")
        if cfg.animate:
            plots.animate_arm(ref.t[:n], ref.x[:n], run["x"], run_dir / "closed_loop.gif")
    return result


@hydra.main(version_base="1.3", config_path="../conf", config_name="closed_loop")
def main(cfg: DictConfig) -> None:
    """CLI: print the headline numbers and where the outputs went."""
    run_dir = Path(hydra.core.hydra_config.HydraConfig.get().runtime.output_dir)
    m = run_cli(lambda: run_closed_loop(cfg, run_dir), "pinnmpc.closed_loop", run_dir)
    print(
        f"{m['status']}: {m['steps']} steps on {m['reference']}"
        + (f" (offset-free, gain {m['disturbance_gain']:g})" if m["disturbance_gain"] > 0 else "")
        + f"; MAE alpha {m['mae']['alpha']:.2e} rad, "
        f"beta {m['mae']['beta']:.2e} rad; OCP median {1e3 * m['ocp_time_s']['median']:.2f} ms "
        f"(plant step {1e3 * m['plant_step_time_s']['median']:.2f} ms); outputs in {run_dir}"
    )
    if m["status"] != "ok":
        sys.exit(1)


if __name__ == "__main__":
    main()
