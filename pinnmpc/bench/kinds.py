"""Section 8: every registered controller kind (pinnmpc.controller.registry) on the bench's reference and plant. The
built-in kinds are measured by their own sections (pinn: 2-5, casadi: 6) and listed with them; any other kind gets
one closed loop, with the network controller's horizon, weights, bounds and limits and its own settings
(kinds.settings.<kind>)."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

from omegaconf import DictConfig, OmegaConf, open_dict

from pinnmpc.bench.loops import loop_row
from pinnmpc.controller.registry import build_registered, controller_kinds
from pinnmpc.references.files import Reference
from pinnmpc.systems.base import System

log = logging.getLogger(__name__)

SHARED = ("horizon", "Q", "R", "R_rate", "u_low", "u_high", "joint_limits")  # what every kind takes from controller
COVERED = {"pinn": "closed_loop", "casadi": "classical"}  # the built-in kinds, by the section that measures them


def kind_config(cfg: DictConfig, kind: str) -> DictConfig:
    """The job's config with `controller` set to kind's: the shared problem from the network controller's settings,
    the rest its own (kinds.settings.<kind>, else its dataclass's defaults)."""
    own = (cfg.kinds.get("settings") or {}).get(kind) or {}
    shared = {k: cfg.controller[k] for k in SHARED if k in cfg.controller}
    out = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    with open_dict(out):
        out.controller = OmegaConf.merge(shared, own, {"kind": kind})
    return out


def bench_kinds(cfg: DictConfig, system: System, ref: Reference, sections: Sequence[str]) -> dict[str, Any]:
    """One row per registered kind: the section that ran it, or its closed loop here."""
    rows: dict[str, Any] = {}
    for kind in controller_kinds():
        if kind in COVERED:
            rows[kind] = {"section": COVERED[kind], "ran": COVERED[kind] in sections}
            continue
        run_cfg = kind_config(cfg, kind)
        controller, domain, tau = build_registered(run_cfg, system)
        rows[kind] = loop_row(run_cfg, system, controller, domain, tau, ref)
        log.info("kinds: %s done (%s)", kind, rows[kind]["status"])
    return {"reference": ref.name, "rows": rows}


def md_kinds(section: dict[str, Any], names: Sequence[str]) -> str:
    """Section 8's table: each kind's worst joint-angle MAE and OCP median, or where it was measured."""
    nq = len(names) // 2
    lines = [
        f"## 8. Controller kinds ({section['reference']})",
        "",
        "Every registered kind (`controller.kind`); a kind a section above runs is measured there.",
        "",
        "| kind | status | worst joint MAE | OCP median (ms) | solver |",
        "|---|---|---|---|---|",
    ]
    for kind, row in section["rows"].items():
        if "section" in row:
            where = f"see section `{row['section']}`" + ("" if row["ran"] else " (off in this run)")
            lines.append(f"| {kind} | {where} | | | |")
            continue
        worst = max(float(row["mae"][n]) for n in names[:nq])
        median = 1e3 * row["ocp_time_s"]["median"]
        lines.append(f"| {kind} | {row['status']} | {worst:.3g} | {median:.3g} | {row['solver']} |")
    return "\n".join([*lines, ""])
