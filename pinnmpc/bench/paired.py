"""OCP time of controllers on the same robot with their samples interleaved in one process.

Closed loops run one after the other on a shared machine see its speed change between them (OCP medians of one
controller moved by up to 2x between runs here), so a ratio of two such medians says little. Here every controller
tracks the reference on its own plant, and sample k of each loop runs back to back, their order alternating from
sample to sample: the host's drift falls on all of them alike, and the per-sample ratio's median is the figure.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from pinnmpc.controller.base import Controller
from pinnmpc.plant.base import Plant, PlantError
from pinnmpc.references import Reference


def paired_ocp(
    controllers: dict[str, Controller],
    plant: Callable[[], Plant],
    ref: Reference,
    max_steps: int | None = None,
    nq: int | None = None,
) -> dict[str, Any]:
    """Each controller on a plant of its own tracks ref from its first sample (at most max_steps samples), the
    loops' samples interleaved;
    OCP median and p95 per controller (as the closed loop's `ocp_time_s`: make_step, estimator included) and each
    one's per-sample ratio to the first controller's; with nq, each loop's worst joint-angle MAE over the samples all
    ran (`worst_mae`). Stops at the first plant failure, saying so in `status`."""
    keys = list(controllers)
    horizon = controllers[keys[0]].horizon
    loops = {k: (c, plant(), np.array(ref.x[0], dtype=np.float64)) for k, c in controllers.items()}
    times: dict[str, list[float]] = {k: [] for k in keys}
    errors: dict[str, list[np.ndarray]] = {k: [] for k in keys}  # |x_k+1 - ref_k+1| of each loop's joint angles
    status = "ok"
    for c, _, _ in loops.values():
        c.reset()
    steps = len(ref) - horizon - 1
    for k in range(steps if max_steps is None else min(steps, int(max_steps))):
        for key in keys if k % 2 == 0 else keys[::-1]:
            c, p, x = loops[key]
            u = c.make_step(x, ref.x[k + 1 : k + 1 + horizon])
            times[key].append(c.stats[-1].time_s)
            try:
                loops[key] = (c, p, p.step(x, u))
                if nq:
                    errors[key].append(np.abs(loops[key][2][:nq] - ref.x[k + 1][:nq]))
            except PlantError as e:
                status = f"plant_failure ({key}, step {k}): {e}"
                break
        if status != "ok":
            break
    n = min(len(t) for t in times.values())
    t = {key: np.array(v[:n]) for key, v in times.items()}
    base = t[keys[0]]
    out = {
        "reference": ref.name,
        "samples": n,
        "status": status,
        "base": keys[0],
        "ocp_median_s": {key: float(np.median(v)) for key, v in t.items()},
        "ocp_p95_s": {key: float(np.percentile(v, 95)) for key, v in t.items()},
        "ratio_median": {key: float(np.median(v / base)) for key, v in t.items()},
    }
    if nq:
        out["worst_mae"] = {key: float(np.mean(errors[key][:n], axis=0).max()) if n else float("nan") for key in keys}
    return out
