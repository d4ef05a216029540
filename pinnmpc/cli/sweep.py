"""Hydra callback that gathers every run of a multirun into one table (CSV and markdown)."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from pinnmpc.util.io import atomic_write
from pinnmpc.util.tables import fmt, md_table

METRICS = ("best_val_rmse_position", "wall_time_s", "epochs")  # train_metrics.json keys in the table


def collect(sweep_dir: Path, swept: set[str] | None = None) -> list[dict[str, Any]]:
    """One row per finished run: its swept overrides (all when swept is None) and its training metrics."""
    rows = []
    for metrics_file in sorted(
        sweep_dir.glob("*/train_metrics.json"), key=lambda p: int(p.parent.name) if p.parent.name.isdigit() else 0
    ):
        run = metrics_file.parent
        overrides_file = run / ".hydra" / "overrides.yaml"
        overrides = OmegaConf.to_container(OmegaConf.load(overrides_file)) if overrides_file.is_file() else []
        m = json.loads(metrics_file.read_text())
        final = m.get("final_metrics", {})
        shown = [o for o in overrides if swept is None or o.split("=", 1)[0].lstrip("+~") in swept]
        row = {"run": run.name, "overrides": " ".join(shown)}
        row.update({k: m.get(k) for k in METRICS})
        row.update({k.removeprefix("val/"): v for k, v in final.items() if k.startswith("val/rmse_")})
        rows.append(row)
    return rows


def write_tables(sweep_dir: Path, rows: list[dict[str, Any]]) -> None:
    """sweep_results.csv and sweep_results.md, best run first."""
    if not rows:
        return
    rows = sorted(
        rows, key=lambda r: float("inf") if r["best_val_rmse_position"] is None else r["best_val_rmse_position"]
    )
    fields = list(dict.fromkeys(k for r in rows for k in r))
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=fields)
    writer.writeheader()
    writer.writerows(rows)
    atomic_write(sweep_dir / "sweep_results.csv", lambda p: p.write_text(buf.getvalue()))

    def cell(v: Any) -> str:
        """One cell in the reports' format; lists and other values as written."""
        return fmt(v) if v is None or isinstance(v, (int, float, str)) else str(v)

    table = md_table(fields, [[cell(r.get(f)) for f in fields] for r in rows])
    atomic_write(sweep_dir / "sweep_results.md", lambda p: p.write_text(table + "\n"))


class SweepTable(Callback):
    """Write the sweep table when a multirun ends (local joblib or SLURM submitit alike)."""

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        """Collect and write; print where the table went."""
        sweep_dir = Path(config.hydra.sweep.dir)
        params = OmegaConf.select(config, "hydra.sweeper.params")
        rows = collect(sweep_dir, set(params) if params else None)
        write_tables(sweep_dir, rows)
        print(f"sweep table ({len(rows)} runs): {sweep_dir / 'sweep_results.md'}")
