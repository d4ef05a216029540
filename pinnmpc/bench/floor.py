"""Section 9: the network controller against its own floor, and its cold start at a long horizon. Per sample the
controller cannot avoid evaluating the network's values and Jacobians at the horizon's nodes and the estimator's one
step; everything else in its OCP time is its own overhead. The floor is timed right after each solve of a real
closed loop, on that sample's nodes (the plan's predicted states and inputs), so both see the same machine at the
same moment (the ratio a shared machine's drift cannot bias)."""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf

from pinnmpc.bench.common import controller_cfg, plant_kind
from pinnmpc.bench.loops import loop_row
from pinnmpc.controller.build import build_nmpc
from pinnmpc.references.files import Reference
from pinnmpc.surrogate.checkpoint import Surrogate
from pinnmpc.surrogate.flowmap import numpy_path, passes_plain_rows
from pinnmpc.systems.base import System
from pinnmpc.util.tables import fmt

log = logging.getLogger(__name__)


class FloorProbe:
    """The controller with the floor timed after each of its solves: the network's step_with_jacobian on the
    horizon's nodes (batch H) and one step (the estimator's), in one pass where the map has one (its
    step_with_jacobian_plus, as the controller's OCP calls it), else two calls."""

    def __init__(self, controller: Any, flow: Any) -> None:
        self.inner, self.flow = controller, flow
        self._plus = passes_plain_rows(flow)
        self.ocp_s: list[float] = []
        self.floor_s: list[float] = []

    def __getattr__(self, name: str) -> Any:
        """Everything else is the controller's (stats, bounds, describe, the monitor)."""
        return getattr(self.inner, name)

    @property
    def delay_periods(self) -> int:
        """The controller's: the closed loop sets it on a plant that runs each command a period late."""
        return self.inner.delay_periods

    @delay_periods.setter
    def delay_periods(self, periods: int) -> None:
        """Set on the controller itself, not on this probe."""
        self.inner.delay_periods = periods

    def make_step(self, x: np.ndarray, x_ref: np.ndarray) -> np.ndarray:
        """The controller's input, then the floor on the plan it just made."""
        start = time.perf_counter()
        u = self.inner.make_step(x, x_ref)
        solved = time.perf_counter()
        plan = self.inner.U.numpy()  # (H, nu): the inputs the next solve starts from
        nodes = np.vstack([np.asarray(x, dtype=np.float64)[None], np.asarray(x_ref, dtype=np.float64)[:-1]])
        floor_start = time.perf_counter()
        if self._plus:
            self.flow.step_with_jacobian_plus(nodes, plan, nodes[:1], plan[:1])
        else:
            self.flow.step_with_jacobian(nodes, plan)
            self.flow.step(nodes[:1], plan[:1])
        done = time.perf_counter()
        self.ocp_s.append(solved - start)
        self.floor_s.append(done - floor_start)
        return u


def bench_floor(cfg: DictConfig, system: System, surrogate: Surrogate, ref: Reference) -> dict[str, Any]:
    """Per horizon of floor.horizons: the configured controller's closed loop on the reference with its floor timed
    sample by sample; the OCP median, the floor median and the median of the per-sample ratio."""
    flow = numpy_path(surrogate) or surrogate
    run_cfg = OmegaConf.merge(cfg, {"closed_loop": {"max_steps": cfg.floor.max_steps}})
    rows = []
    for horizon in cfg.floor.horizons:
        probe = FloorProbe(build_nmpc(controller_cfg(cfg, horizon=int(horizon)), surrogate, system), flow)
        row = loop_row(run_cfg, system, probe, surrogate.domain, surrogate.tau, ref)  # type: ignore[arg-type]
        ocp, floor = np.asarray(probe.ocp_s), np.asarray(probe.floor_s)
        rows.append(
            {
                "horizon": int(horizon),
                "status": row["status"],
                "steps": row["steps"],
                "mae": row["mae"],
                "ocp_median_s": float(np.median(ocp)),
                "floor_median_s": float(np.median(floor)),
                "ratio_median": float(np.median(ocp / floor)),
                "ratio_p95": float(np.percentile(ocp / floor, 95)),
                "iterations_mean": row["iterations_mean"],
            }
        )
        log.info("floor: H=%d done, %.2fx the floor", horizon, rows[-1]["ratio_median"])
    section = {"solver": str(cfg.controller.solver), "reference": ref.name, "rows": rows, "plant": plant_kind(cfg)}
    if cfg.floor.get("cold") is not None and cfg.floor.cold.enabled:
        section["cold"] = bench_cold(cfg, system, surrogate, ref)
    return section


def jumped(ref: Reference, nq: int, jump: float, at: int) -> Reference:
    """The reference with every joint angle raised by jump from sample at on: a step no arm makes in one period."""
    x = np.array(ref.x, dtype=np.float64)
    x[at:, :nq] += jump
    return Reference(t=ref.t, x=x, name=f"{ref.name}, +{jump:g} rad from sample {at}")


def bench_cold(cfg: DictConfig, system: System, surrogate: Surrogate, ref: Reference) -> list[dict[str, Any]]:
    """The cold start at floor.cold.horizon: the first solve of a closed loop (no plan to start from) on the
    reference, and on it with a jump the arm cannot make inside the first horizon; its iterations, and its time
    against the same loop's warm median. floor.cold.repeats such loops on fresh controllers, the ratio formed per loop
    (its cold solve and its warm samples a second apart, so a shared machine's drift between them cannot bias it) and
    its median reported, with the medians of the cold and warm times."""
    c = cfg.floor.cold
    horizon = int(c.horizon)
    run_cfg = OmegaConf.merge(cfg, {"closed_loop": {"max_steps": int(c.max_steps)}})
    rows = []
    settings = controller_cfg(cfg, horizon=horizon)
    for case in (ref, jumped(ref, system.nq, float(c.jump), round(float(c.ahead) * horizon))):
        loops = []
        for _ in range(int(c.repeats)):
            controller = build_nmpc(settings, surrogate, system)
            row = loop_row(run_cfg, system, controller, surrogate.domain, surrogate.tau, case)
            loops.append((row, controller.stats))
        row = loops[0][0]  # the first loop's status
        cold = np.array([s[0].time_s for _, s in loops])
        warm = np.array([np.median([step.time_s for step in s[1:]]) for _, s in loops])
        rows.append(
            {
                "reference": case.name,
                "horizon": horizon,
                "status": row["status"],
                "cold_iterations": int(max(s[0].iterations for _, s in loops)),
                "cold_s": float(np.median(cold)),
                "warm_median_s": float(np.median(warm)),
                "ratio": float(np.median(cold / warm)),
                "warm_iterations_max": int(max(step.iterations for _, s in loops for step in s[1:])),
            }
        )
        log.info("floor: cold start at H=%d, %d iterations", horizon, rows[-1]["cold_iterations"])
    return rows


def md_floor(section: dict[str, Any], names: Sequence[str]) -> str:
    """Section 9's table: the controller's OCP time against its floor, per horizon."""
    nq = len(names) // 2
    lines = [
        f"## 9. The network controller against its floor ({section['solver']}, {section['reference']}, "
        f"plant={section.get('plant', 'scipy')})",
        "",
        "Floor: the network's values and Jacobians at the horizon's nodes and the estimator's one step, timed right "
        "after each solve of the same closed loop; ratio: the median of the per-sample OCP / floor.",
        "",
        "| H | OCP median (ms) | floor median (ms) | ratio (median) | ratio (p95) | iterations | worst joint MAE "
        "| status |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in section["rows"]:
        worst = max(float(r["mae"][n]) for n in names[:nq])
        ocp, floor = fmt(1e3 * r["ocp_median_s"]), fmt(1e3 * r["floor_median_s"])
        lines.append(
            f"| {r['horizon']} | {ocp} | {floor} | {fmt(r['ratio_median'])} | {fmt(r['ratio_p95'])} | "
            f"{fmt(r['iterations_mean'])} | {fmt(worst)} | {r['status']} |"
        )
    if section.get("cold"):
        lines += [
            "",
            "Cold start: the first solve of a closed loop (no plan to start from) against the same loop's warm "
            "median; medians over repeated loops on fresh controllers, the ratio formed per loop.",
            "",
            "| reference | H | cold iterations | cold (ms) | warm median (ms) | cold / warm | warm iterations (max) "
            "| status |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for r in section["cold"]:
            lines.append(
                f"| {r['reference']} | {r['horizon']} | {r['cold_iterations']} | {fmt(1e3 * r['cold_s'])} | "
                f"{fmt(1e3 * r['warm_median_s'])} | {fmt(r['ratio'])} | {r['warm_iterations_max']} | {r['status']} |"
            )
    return "\n".join([*lines, ""])
