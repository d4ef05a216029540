"""Closed loops under measurement noise and plant mismatch, one table: the grid `python -m pinnmpc.robustness` runs."""

from __future__ import annotations

import copy
import itertools
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from pinnmpc.simulation.run import run_closed_loop
from pinnmpc.simulation.settings import validate_robustness
from pinnmpc.systems.registry import build_system
from pinnmpc.util.io import atomic_write, save_json
from pinnmpc.util.tables import md_table


def grid_runs(cfg: DictConfig, run_dir: Path, positions: list[str]) -> list[dict[str, Any]]:
    """One closed loop per (noise sigma, friction scale, mass scale), each in its own subfolder."""
    rows = []
    grid = cfg.robustness
    for sigma, friction, mass in itertools.product(grid.noise_sigma, grid.friction_scale, grid.mass_scale):
        run_cfg = copy.deepcopy(cfg)
        run_cfg.noise_sigma, run_cfg.plant.friction_scale, run_cfg.plant.mass_scale = sigma, friction, mass
        name = f"noise{sigma:g}_friction{friction:g}_mass{mass:g}"
        m = run_closed_loop(run_cfg, run_dir / name)
        worst = max(m["max_abs_error"][k] for k in positions)
        rows.append(
            {
                "noise_sigma": sigma,
                "friction_scale": friction,
                "mass_scale": mass,
                "status": m["status"],
                "mae": m["mae"],
                "max_abs_error": m["max_abs_error"],
                "fallbacks": m["fallbacks"],
                "out_of_box_steps": m["out_of_box_steps"],
                "bounded": m["status"] == "ok" and worst <= grid.bound,
            }
        )
    return rows


def markdown(rows: list[dict[str, Any]], bound: float, positions: list[str]) -> str:
    """The table a reader compares against the nominal row: MAE and worst error of every joint angle."""
    headers = ["noise sigma", "friction scale", "mass scale"]
    headers += [f"MAE {p}" for p in positions] + [f"max err {p}" for p in positions] + ["fallbacks", "bounded"]
    body = [
        [f"{r['noise_sigma']:g}", f"{r['friction_scale']:g}", f"{r['mass_scale']:g}"]
        + [f"{r['mae'][p]:.2e}" for p in positions]
        + [f"{r['max_abs_error'][p]:.2e}" for p in positions]
        + [str(r["fallbacks"]), "yes" if r["bounded"] else "NO"]
        for r in rows
    ]
    return md_table(headers, body) + f"\n\nbounded: status ok and max position error <= {bound:g} rad.\n"


def run_robustness(cfg: DictConfig, run_dir: Path) -> list[dict[str, Any]]:
    """Run the grid, write robustness.json and robustness.md."""
    system = build_system(cfg.system)
    validate_robustness(cfg, system)
    positions = list(system.state_names[: system.nq])
    rows = grid_runs(cfg, run_dir, positions)
    save_json(run_dir / "robustness.json", rows)
    text = markdown(rows, cfg.robustness.bound, positions)
    atomic_write(run_dir / "robustness.md", lambda p: p.write_text(text))
    return rows
