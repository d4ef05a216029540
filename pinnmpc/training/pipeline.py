"""Two stages in one `make train`: a network for part of the budget, then a correction stage on it for the rest.

A single network flattens well before a training budget of tens of minutes ends; a correction network fitted to
what the frozen one still gets wrong keeps improving (Wang and Lai 2024, docs/design.md). With `stage.split` set,
`pinnmpc.train` runs the base into `<run dir>/base/` for that fraction of `trainer.max_time`, then the stage into
the run dir itself for the time left, so the run dir's surrogate.pt is the merged network as always.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf, open_dict

from pinnmpc.util.checks import SettingError
from pinnmpc.util.io import save_json

Trainer = Callable[[DictConfig, Path], dict[str, Any]]  # train(cfg, run_dir) with the CLI's other arguments bound


def seconds(max_time: str) -> float:
    """Lightning's DD:HH:MM:SS as seconds."""
    d, h, m, s = (int(p) for p in max_time.strip().split(":"))
    return float(((d * 24 + h) * 60 + m) * 60 + s)


def duration(total_s: float) -> str:
    """Seconds as Lightning's DD:HH:MM:SS (whole seconds, at least one)."""
    s = max(1, int(round(total_s)))
    return f"{s // 86400:02d}:{s // 3600 % 24:02d}:{s // 60 % 60:02d}:{s % 60:02d}"


def split_budget(cfg: DictConfig) -> float | None:
    """The base network's share of the budget, or None for one network (checked: needs trainer.max_time)."""
    split = cfg.stage.get("split")
    if split is None or cfg.stage.base:
        return None
    if isinstance(split, bool) or not isinstance(split, int | float) or not 0 < split < 1:
        raise SettingError(f"stage.split={split!r}: expected a fraction in (0, 1) of trainer.max_time, or null")
    if not cfg.trainer.get("max_time"):
        raise SettingError("stage.split needs trainer.max_time (DD:HH:MM:SS): the budget it splits; got null")
    return float(split)


def _phase_cfg(cfg: DictConfig, max_time: str, resume: bool, base: str | None) -> DictConfig:
    """A copy of cfg for one phase: its own budget, no split, the stage's base and loss settings if any."""
    out = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    with open_dict(out):
        out.trainer.max_time = max_time
        out.stage.split = None
        out.stage.base = base
        out.resume = resume
        out.ckpt_path = None
        if base is not None:
            out.module.robust_delta = cfg.stage.robust_delta
    return out


def _finished(run_dir: Path) -> dict[str, Any] | None:
    """The summary of a phase that ended normally and left its surrogate, else None."""
    metrics = run_dir / "train_metrics.json"
    if not (metrics.is_file() and (run_dir / "surrogate.pt").is_file()):
        return None
    summary = json.loads(metrics.read_text())
    return summary if summary.get("status") == "ok" else None


def train_in_stages(cfg: DictConfig, run_dir: Path, fit: Trainer, resume_command: str | None = None) -> dict[str, Any]:
    """Base for split x the budget, then a correction stage for what the base left of it; resumable in either phase
    (resume=true with this run dir picks up the phase that was running; an interrupted phase's summary says so)."""
    split = split_budget(cfg)
    if split is None:
        return fit(cfg, run_dir)
    budget = seconds(cfg.trainer.max_time)
    base_dir = run_dir / "base"
    base = _finished(base_dir)
    if base is None:
        resume_base = bool(cfg.resume) and (base_dir / "checkpoints" / "last.ckpt").is_file()
        base = fit(_phase_cfg(cfg, duration(split * budget), resume_base, None), base_dir)
        if base["status"] != "ok":
            if base.get("resume_command"):
                base["resume_command"] = resume_command
            return base
    left = budget - float(base["training_time_s"])
    if left < 1:
        raise SettingError(f"stage.split={cfg.stage.split} left no time for the stage of trainer.max_time")
    resume_stage = bool(cfg.resume) and (run_dir / "checkpoints" / "last.ckpt").is_file()
    stage_cfg = _phase_cfg(cfg, duration(left), resume_stage, str(base_dir / "surrogate.pt"))
    summary = fit(stage_cfg, run_dir)
    summary["base_run"] = str(base_dir)
    if summary.get("resume_command"):
        summary["resume_command"] = resume_command
    if (run_dir / "train_metrics.json").is_file():  # the stage wrote its own: the file says what the command did
        save_json(run_dir / "train_metrics.json", summary)
    return summary


def base_training_time(base: str | None) -> float:
    """Training time behind a stage's frozen base or init_from network (its surrogate's meta, or a training
    checkpoint's timer; 0 without one), so training_time_s counts every network a run is made of."""
    if not base or not Path(base).is_file():
        return 0.0
    if str(base).endswith(".ckpt"):
        import torch

        ckpt = torch.load(base, map_location="cpu", weights_only=True)
        timer = (ckpt.get("callbacks") or {}).get("Timer") or {}
        before = (ckpt.get("pinnmpc") or {}).get("base_training_time_s") or 0.0  # its own base (0: none)
        return float(timer.get("time_elapsed", {}).get("train") or 0.0) + float(before)
    from pinnmpc.surrogate.checkpoint import load_surrogate

    return float(load_surrogate(base).meta.get("training_time_s") or 0.0)
