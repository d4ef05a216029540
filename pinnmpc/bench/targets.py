"""Section 5: the system's targets (conf/system/<name>.yaml `targets`) next to this run's numbers."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from omegaconf import DictConfig


def _target(what: str, value: float, limit: float) -> dict[str, Any]:
    """One target: met when the measured value is at most the limit."""
    return {"what": what, "value": float(value), "limit": float(limit), "met": bool(value <= limit)}


def _per_state(what: str, values: dict[str, float], names: Sequence[str], limits: Sequence[Any] | None) -> list:
    """Targets per state where the limit is set (null: none); a list of the wrong length is a config error."""
    if limits is None:
        return []
    if len(limits) != len(names):
        raise ValueError(f"targets for {what} list {len(limits)} limits; expected one per state {list(names)}")
    return [_target(f"{what} {n}", values[n], lim) for n, lim in zip(names, limits) if lim is not None]


def check_targets(cfg: DictConfig, result: dict[str, Any], names: Sequence[str]) -> list[dict[str, Any]]:
    """The project's targets next to this run's numbers, for the sections that ran."""
    t = cfg.targets
    rows = []
    if "step" in result:
        rows += _per_state("one-step RMSE", result["step"]["rmse"]["pinn_numpy"], names, t.one_step_rmse)
    row = result.get("closed_loop", {}).get("rows", {}).get(f"pinn_{cfg.controller.solver}")
    if row is not None:
        where = f"closed loop on {result['closed_loop']['reference']}: MAE"
        rows += _per_state(where, row["mae"], names, t.closed_loop_mae)
        rows.append(_target("OCP median / plant step median", row["ratio_ocp_to_plant"], t.ocp_median_ratio))
        p95_ratio = row["ocp_time_s"]["p95"] / row["plant_step_median_s"]
        rows.append(_target("OCP p95 / plant step median", p95_ratio, t.ocp_p95_ratio))
    return rows
