"""Section 10: the network controller against its peers on the same network. A peer runs the exported flow map
(pinnmpc.surrogate.casadi_network) the way its best users would: CasADi's real-time iteration with the QP data
compiled to C and qrqp or HPIPM (the classical NMPC with controller.transcription=network); acados' real-time
iteration and l4casadi where installed, else a line saying why not. Same reference, plant, horizon, weights, bounds
and offset-free estimator. Each peer is paired with ours alone, samples interleaved in one process (bench/paired.py):
each side runs right after its own last sample in half the samples and right after the other's in the rest, so both
see the same cache history (with a third controller in the interleave one side would follow two strangers where the
other follows one). The per-pair ratios are the figure."""

from __future__ import annotations

import importlib.util
import logging
from typing import Any

from omegaconf import DictConfig, OmegaConf

from pinnmpc.bench.classical import classical_cfg
from pinnmpc.bench.common import controller_cfg, make_plant, plant_kind
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
    """Per horizon of peers.horizons: the network controller and each CasADi peer (peers.qpsols), pair by pair, track
    the reference with their samples interleaved; per pair both OCP medians, the per-sample ratio to ours and each
    one's worst joint MAE (`pairs`, by the peer's name), and the fastest peer's name (`fastest`; None without peers)."""
    rows = []
    plant = lambda: make_plant(cfg, system, surrogate.tau)  # noqa: E731
    for horizon in cfg.peers.horizons:
        ours = build_nmpc(controller_cfg(cfg, horizon=int(horizon)), surrogate, system)
        pairs = {}
        for qpsol in cfg.peers.qpsols:
            name = f"casadi_rti_{qpsol}"
            peer = build_casadi_nmpc(peer_cfg(cfg, int(horizon), str(qpsol)), system)
            pairs[name] = paired_ocp({OURS: ours, name: peer}, plant, ref, cfg.peers.max_steps, system.nq)
        fastest = min(pairs, key=lambda k: pairs[k]["ratio_median"][k], default=None)
        rows.append({"horizon": int(horizon), "pairs": pairs, "fastest": fastest})
        if fastest is not None:
            ratio = pairs[fastest]["ratio_median"][fastest]
            log.info("peers: H=%d, the fastest peer %s at %.2fx ours", horizon, fastest, ratio)
    section = {"solver": str(cfg.controller.solver), "reference": ref.name, "rows": rows, "missing": missing_peers()}
    return {**section, "plant": plant_kind(cfg)}


def md_peers(section: dict[str, Any]) -> str:
    """Section 10's table: per pair, the peer's OCP time and ours on the same network, interleaved."""
    if "skipped" in section:
        return f"## 10. Peers on the same network\n\nSkipped: {section['skipped']}.\n"
    lines = [
        f"## 10. Peers on the same network ({section['solver']} against CasADi's real-time iteration on the exported "
        f"flow map, {section['reference']}, plant={section.get('plant', 'scipy')})",
        "",
        "Each peer paired with ours, samples interleaved in one process; peer / ours: the median of the per-sample OCP "
        "ratio (above 1: ours is faster).",
        "",
        "| H | peer | peer OCP median (ms) | peer OCP p95 (ms) | ours, same pair (ms) | peer / ours "
        "| worst joint MAE, peer / ours | samples | status |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in section["rows"]:
        for key, p in r["pairs"].items():
            median, p95, mae = p["ocp_median_s"], p["ocp_p95_s"], p["worst_mae"]
            lines.append(
                f"| {r['horizon']} | {key} | {fmt(1e3 * median[key])} | {fmt(1e3 * p95[key])} "
                f"| {fmt(1e3 * median[OURS])} | {fmt(p['ratio_median'][key])} | {fmt(mae[key])} / {fmt(mae[OURS])} "
                f"| {p['samples']} | {p['status']} |"
            )
    lines += ["", *(f"- {name}: {why}" for name, why in section.get("missing", {}).items())]
    return "\n".join([*lines, ""])
