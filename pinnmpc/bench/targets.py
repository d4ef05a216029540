"""Section 5: the system's targets (conf/system/<name>.yaml `targets`) next to this run's numbers."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from omegaconf import DictConfig


def _target(what: str, value: float, limit: float, at_least: bool = False) -> dict[str, Any]:
    """One target: met when the measured value is at most the limit (at_least: at least it, a speed-up)."""
    met = value >= limit if at_least else value <= limit
    return {"what": what, "value": float(value), "limit": float(limit), "met": bool(met), "at_least": at_least}


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
    return rows + speed_targets(t, result)


def by_horizon(limits: Any) -> dict[int, float]:
    """A per-horizon limit mapping ({5: 2.0, 20: 2.5}; keys as numbers or digit strings) as {horizon: limit}."""
    return {} if limits is None else {int(h): float(v) for h, v in limits.items()}


def speed_targets(t: DictConfig, result: dict[str, Any]) -> list[dict[str, Any]]:
    """The network controller's speed targets, for the sections that ran: its OCP over its floor per horizon (9),
    its cold start at a long horizon (9), the fastest peer's OCP over ours per horizon (10) and the classical NMPC's
    over ours interleaved (6); a target set to null is none."""
    rows = []
    floor, limits = result.get("floor") or {}, by_horizon(t.get("floor_ratio"))
    for r in floor.get("rows", []):
        if r["horizon"] in limits:
            rows.append(_target(f"OCP / floor (median), H = {r['horizon']}", r["ratio_median"], limits[r["horizon"]]))
    for r, case in zip(floor.get("cold", []), ("", ", after a jump"), strict=False):
        where = f"cold start at H = {r['horizon']}{case}"
        if t.get("cold_iterations") is not None:
            rows.append(_target(f"{where}: iterations", r["cold_iterations"], t.cold_iterations))
        if t.get("cold_ratio") is not None:
            rows.append(_target(f"{where}: time / warm median", r["ratio"], t.cold_ratio))
    if t.get("peer_speedup") is not None:
        for r in (result.get("peers") or {}).get("rows", []):
            name = r["fastest"]  # bench_peers names it
            if name is not None:
                ratio = r["pairs"][name]["ratio_median"][name]
                rows.append(_target(f"fastest peer's OCP / ours, H = {r['horizon']}", ratio, t.peer_speedup, True))
    paired = (result.get("classical") or {}).get("paired")
    if paired and t.get("classical_speedup") is not None:
        theirs = next(k for k in paired["ratio_median"] if k != paired["base"])
        what = "classical NMPC's OCP / ours, interleaved"
        rows.append(_target(what, paired["ratio_median"][theirs], t.classical_speedup, True))
    return [{**r, "speed": True} for r in rows]
