"""`python -m pinnmpc.train [overrides]`: train a PINN surrogate; outputs go to the Hydra run dir."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import hydra
import lightning as L
import torch
from hydra.utils import instantiate
from lightning.pytorch.callbacks import Timer
from omegaconf import DictConfig, OmegaConf

from pinnmpc.cli import run_cli
from pinnmpc.io import save_json
from pinnmpc.pinn import PINN, StagedPINN
from pinnmpc.surrogate import load_surrogate
from pinnmpc.systems.base import System
from pinnmpc.training.callbacks import AtomicCheckpoint, SelfLoopFigure, SurrogateFacts
from pinnmpc.training.data import flow_scale
from pinnmpc.training.stage import staged_model


def build_model(cfg: DictConfig, system: System) -> PINN | StagedPINN:
    """The network for this system's training box (output scale estimated from the flow when 'auto'), or with
    stage.base a correction network on top of that trained one."""
    if cfg.stage.base:
        return build_staged(cfg, system)
    scale = cfg.model.output_scale
    if scale == "auto":
        a = cfg.model.auto_scale
        scale = flow_scale(system, cfg.t_max, a.samples, a.h, a.quantile, cfg.seed)
    return PINN(
        state_low=system.state_box.low,
        state_high=system.state_box.high,
        input_low=system.input_box.low,
        input_high=system.input_box.high,
        t_max=cfg.t_max,
        hidden=list(cfg.model.hidden),
        activation=cfg.model.activation,
        ic=cfg.model.ic,
        output_scale=None if scale is None else list(scale),
        time_basis=list(cfg.model.time_basis) if cfg.model.ic == "gated" else [],
        second_order=cfg.model.get("second_order", False),
        periodic=list(cfg.model.get("periodic", [])),
    )


def build_staged(cfg: DictConfig, system: System) -> StagedPINN:
    """stage.base frozen plus a correction network of stage.hidden; the base fixes box, t_max and form."""
    st = cfg.stage
    model = staged_model(
        system, st.base, cfg.tau, list(st.hidden), st.error_scale, st.first_layer_gain, st.last_layer_gain,
        st.samples, st.h, cfg.seed,
    )  # fmt: skip
    if abs(model.t_max - cfg.t_max) > 1e-12:
        raise ValueError(f"stage.base was trained on t in [0, {model.t_max}]; set t_max={model.t_max}, got {cfg.t_max}")
    return model


def training_time(trainer: L.Trainer, wall: float) -> float:
    """Training time across resumes: Lightning's Timer (there whenever max_time is set) restores what earlier
    processes spent from the checkpoint; without it, this process's wall time."""
    timer = next((c for c in trainer.callbacks if isinstance(c, Timer)), None)
    return wall if timer is None else max(wall, float(timer.time_elapsed("train")))


def resolve_ckpt(cfg: DictConfig, run_dir: Path) -> str | None:
    """Checkpoint to resume from: an explicit ckpt_path, or with resume=true this run dir's last.ckpt."""
    if cfg.ckpt_path:
        path = Path(cfg.ckpt_path)
        if not path.is_file():
            raise FileNotFoundError(f"ckpt_path={cfg.ckpt_path} does not exist; expected a Lightning .ckpt file")
        return str(path)
    last = run_dir / "checkpoints" / "last.ckpt"
    return str(last) if cfg.resume and last.is_file() else None


def train(cfg: DictConfig, run_dir: Path, command: str = "python -m pinnmpc.train") -> dict[str, Any]:
    """Fit, export the best network as surrogate.pt, and return its validation metrics."""
    L.seed_everything(cfg.seed, workers=True)
    torch.set_num_threads(cfg.threads)
    system: System = instantiate(cfg.system)
    model = build_model(cfg, system)
    # _convert_="all": plain lists, not OmegaConf ones, reach the hyper-parameters stored in checkpoints,
    # which load_surrogate reads with torch.load(weights_only=True)
    datamodule = instantiate(cfg.data, _partial_=True, _convert_="all")(
        system=system, tau=cfg.tau, t_max=cfg.t_max, seed=cfg.seed
    )
    module = instantiate(cfg.module, _partial_=True, _convert_="all")(system=system, model=model, tau=cfg.tau)
    ckpt_dir = run_dir / "checkpoints"
    best = AtomicCheckpoint(dirpath=ckpt_dir, filename="best", monitor="val/rmse_position", mode="min")
    last = AtomicCheckpoint(  # every epoch, so a killed run loses at most one epoch of work
        dirpath=ckpt_dir, filename="last", every_n_epochs=1, save_on_train_epoch_end=True, enable_version_counter=False
    )
    figure = SelfLoopFigure(
        cfg.self_loop_figure.every_n_epochs, cfg.self_loop_figure.steps, cfg.self_loop_figure.amplitude
    )
    callbacks = [best, last, SurrogateFacts(cfg.tau), figure]
    logger = L.pytorch.loggers.TensorBoardLogger(save_dir=str(run_dir), name="tensorboard", version="")
    trainer: L.Trainer = instantiate(cfg.trainer, callbacks=callbacks, logger=logger, default_root_dir=str(run_dir))
    start = time.perf_counter()
    trainer.fit(module, datamodule=datamodule, ckpt_path=resolve_ckpt(cfg, run_dir))
    wall = time.perf_counter() - start
    source = best.best_model_path or last.best_model_path
    surrogate = load_surrogate(source)
    metrics = {k: float(v) for k, v in trainer.callback_metrics.items()}
    surrogate.meta = {
        "trained_with": command,
        "config": OmegaConf.to_container(cfg, resolve=True),
        "wall_time_s": wall,
        "training_time_s": training_time(trainer, wall),
        "epochs": trainer.current_epoch,
        "best_val_rmse_position": float(best.best_model_score) if best.best_model_score is not None else None,
        "final_metrics": metrics,
    }
    surrogate.save(run_dir / "surrogate.pt")
    summary = {"wall_time_s": wall, "epochs": trainer.current_epoch, "best_checkpoint": source, **surrogate.meta}
    summary.pop("config")
    save_json(run_dir / "train_metrics.json", summary)
    return summary


@hydra.main(version_base="1.3", config_path="../conf", config_name="train")
def main(cfg: DictConfig) -> float:
    """CLI: returns the best validation position RMSE, so Optuna sweeps can minimise it."""
    hydra_cfg = hydra.core.hydra_config.HydraConfig.get()
    run_dir = Path(hydra_cfg.runtime.output_dir)
    command = " ".join(["python -m pinnmpc.train", *hydra_cfg.overrides.task])
    summary = run_cli(lambda: train(cfg, run_dir, command), "pinnmpc.train", run_dir)
    score = summary["best_val_rmse_position"]
    if score is None:  # the run ended before its first validation epoch
        every = cfg.trainer.check_val_every_n_epoch
        print(f"no validation ran (trainer.check_val_every_n_epoch={every}); outputs in {run_dir}")
        return float("inf")
    print(f"best val RMSE (positions) {score:.3e} rad; surrogate: {run_dir / 'surrogate.pt'}")
    return score


if __name__ == "__main__":
    main()
