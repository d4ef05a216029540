"""Resuming a run: which Lightning checkpoint, and whether it fits this run's settings and network."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import lightning as L
import torch
from omegaconf import DictConfig, OmegaConf

from pinnmpc.surrogate.checkpoint import FORMAT, load_surrogate
from pinnmpc.training.pipeline import seconds
from pinnmpc.util.io import save_json

log = logging.getLogger(__name__)

EXPECTED_CKPT = "expected a Lightning .ckpt written by pinnmpc.train (e.g. <run dir>/checkpoints/last.ckpt)"

LIGHTNING_KEYS = ("pytorch-lightning_version", "state_dict", "optimizer_states", "loops", "epoch", "global_step")


def resolve_ckpt(cfg: DictConfig, run_dir: Path) -> str | None:
    """Checkpoint to resume from: an explicit ckpt_path, or with resume=true this run dir's last.ckpt (which must
    exist: a resume that silently started over would discard the earlier run's work)."""
    if cfg.ckpt_path:
        path = Path(cfg.ckpt_path)
        if not path.is_file():
            what = "is a folder" if path.is_dir() else "does not exist"
            raise FileNotFoundError(f"ckpt_path={cfg.ckpt_path} {what}; {EXPECTED_CKPT}")
        return str(path)
    if not cfg.resume:
        return None
    last = run_dir / "checkpoints" / "last.ckpt"
    if not last.is_file():
        raise FileNotFoundError(
            f"resume=true but {last} does not exist; expected the run dir of an earlier training run "
            "(pass it as hydra.run.dir=<that dir>)"
        )
    return str(last)


def read_ckpt(path: str, label: str) -> dict[str, Any]:
    """A Lightning training checkpoint's contents, or a one-line error naming the file and what was expected."""
    with open(path, "rb") as f:
        head = f.read(4)
    if not (head.startswith(b"PK\x03\x04") or head.startswith(b"\x80")):  # torch's zip format, or a legacy pickle
        raise ValueError(f"{label} is not a torch file (starts with {head!r}); {EXPECTED_CKPT}")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises many types for a file that is not a checkpoint
        detail = str(e).strip().splitlines()[0].split(". ")[0][:100] if str(e).strip() else ""
        reason = f"{type(e).__name__}: {detail}" if detail else type(e).__name__
        raise ValueError(
            f"{label} cannot be read ({reason}; corrupt, truncated or not a torch file); {EXPECTED_CKPT}"
        ) from None
    if isinstance(ckpt, dict) and ckpt.get("format") == FORMAT:
        raise ValueError(f"{label} is an exported surrogate (weights only, no optimizer state); {EXPECTED_CKPT}")
    missing = [k for k in LIGHTNING_KEYS if not isinstance(ckpt, dict) or k not in ckpt]
    if missing:
        raise ValueError(f"{label} is not a Lightning training checkpoint (no {', '.join(missing)}); {EXPECTED_CKPT}")
    return ckpt


def recorded_best(ckpt: dict[str, Any]) -> float | None:
    """The best validation RMSE a training checkpoint's 'best' callback had recorded (None: none)."""
    for key, state in ckpt.get("callbacks", {}).items():
        if "val/rmse_position" in key and isinstance(state, dict) and state.get("best_model_score") is not None:
            return float(state["best_model_score"])
    return None


def spent_budget(cfg: DictConfig, ckpt: dict[str, Any], label: str) -> str | None:
    """Why this configuration has no budget left to train the checkpoint on (None: it has), as a one-line error:
    a spent trainer.max_time or max_epochs runs no epoch and would rewrite the run's results from nothing."""
    spent = ((ckpt.get("callbacks") or {}).get("Timer") or {}).get("time_elapsed", {}).get("train")
    budget = cfg.trainer.get("max_time")
    if budget and spent is not None and spent >= seconds(str(budget)):
        return (
            f"{label} has trained {spent / 60:.1f} min, so trainer.max_time={budget} is spent; expected a longer "
            "trainer.max_time to continue"
        )
    limit, done = cfg.trainer.get("max_epochs"), int(ckpt.get("epoch", -1)) + 1
    if limit is not None and limit != -1 and done >= limit:
        return (
            f"{label} has trained {done} epochs, so trainer.max_epochs={limit} is reached; expected a larger "
            "trainer.max_epochs to continue"
        )
    return None


def check_continuable(cfg: DictConfig, ckpt: dict[str, Any], label: str) -> None:
    """A checkpoint this configuration can train on: the same optimizer (its state is restored), and budget left."""
    have, want = (ckpt.get("hyper_parameters") or {}).get("optimizer"), cfg.module.get("optimizer")
    if have is not None and have != want:
        raise ValueError(
            f"{label} was trained with module.optimizer={have}, this configuration has module.optimizer={want}; "
            "expected the same (its optimizer state is restored, as far as it is saved), or "
            "init_from=<its surrogate.pt> to start anew"
        )
    spent = spent_budget(cfg, ckpt, label)
    if spent:
        raise ValueError(spent)


def finish_spent_run(cfg: DictConfig, run_dir: Path, ckpt: dict[str, Any], command: str) -> dict[str, Any]:
    """A run killed after its budget was spent but before it wrote surrogate.pt: write its best network and
    train_metrics.json from its checkpoints, training nothing (what resume=true does for such a run)."""
    ckpt_dir = run_dir / "checkpoints"
    source = next((p for p in (ckpt_dir / "best.ckpt", ckpt_dir / "last.ckpt") if p.is_file()), None)
    if source is None:
        raise FileNotFoundError(f"{ckpt_dir} holds neither best.ckpt nor last.ckpt; expected a training run dir")
    timer = ((ckpt.get("callbacks") or {}).get("Timer") or {}).get("time_elapsed", {}).get("train") or 0.0
    base = float((ckpt.get("pinnmpc") or {}).get("base_training_time_s") or 0.0)
    meta = {
        "trained_with": command,
        "config": OmegaConf.to_container(cfg, resolve=True),
        "status": "ok",
        "finished_from_checkpoint": True,  # its budget was spent when it was killed: nothing trained on resume
        "wall_time_s": 0.0,
        "training_time_s": float(timer) + base,
        "base_training_time_s": base,
        "epochs": int(ckpt.get("epoch", -1)) + 1,
        "best_val_rmse_position": recorded_best(ckpt),
        "resumed_best_val_rmse_position": recorded_best(ckpt),
        "final_metrics": {},
    }
    surrogate = load_surrogate(str(source))
    surrogate.meta = meta
    surrogate.save(run_dir / "surrogate.pt")
    summary = {**meta, "best_checkpoint": str(source)}
    summary.pop("config")
    save_json(run_dir / "train_metrics.json", summary)
    log.info("resume=true: the budget was already spent; wrote %s from %s", run_dir / "surrogate.pt", source.name)
    return summary


def check_fits(ckpt: dict[str, Any], label: str, module: L.LightningModule) -> None:
    """The checkpoint's network has this configuration's parameter shapes (else Lightning fails mid-restore)."""
    have = {k: tuple(v.shape) for k, v in ckpt["state_dict"].items() if isinstance(v, torch.Tensor)}
    want = {k: tuple(v.shape) for k, v in module.state_dict().items()}
    if have != want:
        diff = next((k for k in sorted(set(have) | set(want)) if have.get(k) != want.get(k)), "")
        inputs = diff.endswith("layers.0.weight") and have.get(diff, (0,))[0] == want.get(diff, (0,))[0]
        hint = " (other network inputs: see system.network.periodic and angle_sums)" if inputs else ""
        raise ValueError(
            f"{label} holds another network ({diff}: {have.get(diff)} in the file, {want.get(diff)} here{hint}); "
            "expected a checkpoint of this configuration (same system, model and stage settings: repeat the run's "
            "overrides, as its train_metrics.json `trained_with` names them)"
        )
    stored = ckpt.get("pinnmpc", {}).get("model", {})
    have_prior, want_prior = stored.get("prior"), getattr(module.model, "config", {}).get("prior")
    # same shapes, another function: the prior is not in the weights. Its kind and arm must match; the arm's
    # description may change on resume (the run trains on, with this configuration's arm)
    have, want = ((p or {}).get("kind") or "null" for p in (have_prior, want_prior))
    if stored and have != want:
        raise ValueError(
            f"{label} holds a network trained with model.prior={have}, this configuration has "
            f"model.prior={want}; expected the same (override system.network.prior={have})"
        )
    arms = [(p or {}).get("system") for p in (have_prior, want_prior)]
    if stored and have != "null" and arms[0] != arms[1]:
        raise ValueError(
            f"{label} holds a network whose prior is the arm {arms[0]!r}, this configuration's is {arms[1]!r}; "
            "expected the same system"
        )


def portable_ckpt(ckpt: dict[str, Any]) -> dict[str, Any]:
    """A training checkpoint to ship: its checkpoint callbacks' absolute paths (the developer's run dir, which
    Lightning prints on resume) become run-relative `checkpoints/<file>`; weights and scores stay."""

    def rel(path: Any) -> Any:
        """`checkpoints/<name>` for a path string, other values as they are."""
        return f"checkpoints/{Path(path).name}" if isinstance(path, str) and path else path

    for state in (ckpt.get("callbacks") or {}).values():
        if not isinstance(state, dict) or "dirpath" not in state:
            continue
        state["dirpath"] = "checkpoints"
        for key in ("best_model_path", "kth_best_model_path", "last_model_path"):
            if key in state:
                state[key] = rel(state[key])
        if isinstance(state.get("best_k_models"), dict):
            state["best_k_models"] = {rel(k): v for k, v in state["best_k_models"].items()}
    return ckpt
