"""Section 10: the network controller against its peers on the same network. A peer runs the exported flow map
(pinnmpc.surrogate.casadi_network) the way its best users would: CasADi's real-time iteration with the QP data
compiled to C and qrqp or HPIPM (the classical NMPC with controller.transcription=network); acados' real-time
iteration and l4casadi where installed, else a line saying why not. Same reference, plant, horizon, weights, bounds
and offset-free estimator; samples interleaved in one process (bench/paired.py), so the ratios are the figure."""

from __future__ import annotations

import importlib.util
import logging
from typing import Any

from omegaconf import DictConfig, OmegaConf

from pinnmpc.bench.classical import classical_cfg
from pinnmpc.bench.common import controller_cfg, make_plant
from pinnmpc.bench.paired import paired_ocp
from pinnmpc.controller.build import build_nmpc
from pinnmpc.controller.classical.nmpc import build_casadi_nmpc
from pinnmpc.references.files import Reference
from pinnmpc.surrogate.checkpoint import Surrogate
from pinnmpc.systems.base import System
from pinnmpc.util.tables import fmt

log = logging.getLogger(__name__)

OURS = "pinn"  # the network controller's row: every ratio is to it
UNINSTALLABLE = {  # peers that need a package pip cannot install here: (module, why not, what it would be)
    "acados": ("acados_template", "acados is not on PyPI: it needs its C library built from source"),
    "l4casadi": ("l4casadi", "l4casadi builds against the installed torch from source (no wheel)"),
}


def peer_cfg(cfg: DictConfig, horizon: int, qpsol: str) -> DictConfig:
    """The classical NMPC on the bench's network (checkpoint) as a real-time iteration with qpsol, sharing
    peers.shared (weights, bounds, limits, estimator) with the network controller at this horizon."""
    own = {"transcription": "network", "network": cfg.checkpoint, "rti": True, "qpsol": qpsol, "horizon": horizon}
    return OmegaConf.merge(classical_cfg(cfg, "sqpmethod", cfg.peers.shared), own)


def missing_peers() -> dict[str, str]:
    """The peers that cannot run here, each with one line saying why."""
    return {
        name: f"skipped: {module} is not installed ({why})"
        for name, (module, why) in UNINSTALLABLE.items()
        if importlib.util.find_spec(module) is None
    }


def bench_peers(cfg: DictConfig, system: System, surrogate: Surrogate, ref: Reference) -> dict[str, Any]:
    """Per horizon of peers.horizons: the network controller and each CasADi peer (peers.qpsols) track the reference
    with their samples interleaved; OCP medians, per-sample ratios to ours and each one's worst joint MAE."""
    rows = []
    for horizon in cfg.peers.horizons:
        controllers = {OURS: build_nmpc(controller_cfg(cfg, horizon=int(horizon)), surrogate, system)}
        for qpsol in cfg.peers.qpsols:
            controllers[f"casadi_rti_{qpsol}"] = build_casadi_nmpc(peer_cfg(cfg, int(horizon), str(qpsol)), system)
        paired = paired_ocp(
            controllers, lambda: make_plant(cfg, system, surrogate.tau), ref, cfg.peers.max_steps, system.nq
        )
        rows.append({"horizon": int(horizon), **paired})
        fastest = min((k for k in controllers if k != OURS), key=lambda k: paired["ratio_median"][k], default=None)
        if fastest is not None:
            log.info(
                "peers: H=%d, the fastest peer %s at %.2fx ours", horizon, fastest, paired["ratio_median"][fastest]
            )
    return {"solver": str(cfg.controller.solver), "reference": ref.name, "rows": rows, "missing": missing_peers()}


def md_peers(section: dict[str, Any]) -> str:
    """Section 10's table: OCP time of ours and of each peer on the same network, interleaved."""
    if "skipped" in section:
        return f"## 10. Peers on the same network\n\nSkipped: {section['skipped']}.\n"
    lines = [
        f"## 10. Peers on the same network ({section['solver']} against CasADi's real-time iteration on the exported "
        f"flow map, {section['reference']})",
        "",
        "Samples interleaved in one process; peer / ours: the median of the per-sample OCP ratio (above 1: ours is "
        "faster).",
        "",
        "| H | controller | OCP median (ms) | OCP p95 (ms) | peer / ours | worst joint MAE | samples | status |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in section["rows"]:
        for key in r["ocp_median_s"]:
            ratio = "1" if key == r["base"] else fmt(r["ratio_median"][key])
            lines.append(
                f"| {r['horizon']} | {key} | {fmt(1e3 * r['ocp_median_s'][key])} | {fmt(1e3 * r['ocp_p95_s'][key])} "
                f"| {ratio} | {fmt(r['worst_mae'][key])} | {r['samples']} | {r['status']} |"
            )
    lines += ["", *(f"- {name}: {why}" for name, why in section.get("missing", {}).items())]
    return "\n".join([*lines, ""])
