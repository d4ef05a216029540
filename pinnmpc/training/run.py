"""A training run from its config: network, data, Lightning trainer and callbacks, resume, and the files it leaves."""

from __future__ import annotations

import hashlib
import logging
import sys
import time
from pathlib import Path
from typing import Any

import lightning as L
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.errors import InstantiationException
from hydra.types import RunMode
from hydra.utils import instantiate
from lightning.pytorch.callbacks import Timer
from omegaconf import DictConfig, OmegaConf

from pinnmpc.robot_data.residual_model import physics_model
from pinnmpc.surrogate.checkpoint import load_surrogate
from pinnmpc.surrogate.network import PINN
from pinnmpc.systems.base import System
from pinnmpc.systems.previous_input import WithPreviousInput
from pinnmpc.systems.registry import build_system
from pinnmpc.training.callbacks import AtomicCheckpoint, GracefulStop, SelfLoopFigure, SurrogateFacts
from pinnmpc.training.data import CollocationDataModule
from pinnmpc.training.job_settings import validate_train
from pinnmpc.training.models import build_model
from pinnmpc.training.pipeline import base_training_time, train_in_stages
from pinnmpc.training.progress import BudgetBar, EpochLog, TrainingClock, quiet_lightning, timer_of
from pinnmpc.training.resume import (
    check_continuable,
    check_fits,
    finish_spent_run,
    read_ckpt,
    recorded_best,
    resolve_ckpt,
    spent_budget,
)
from pinnmpc.util.commands import command_line, override
from pinnmpc.util.io import save_json
from pinnmpc.util.signals import StopSignal
from pinnmpc.util.threads import use_threads

log = logging.getLogger(__name__)


def training_time(trainer: L.Trainer, wall: float | None = None) -> float:
    """Training time across processes: the Timer (train() always has one) starts from what the checkpoint it
    resumed from had counted; the time a killed process spent after its last checkpoint is not in it."""
    timer = timer_of(trainer)
    if timer is None:
        return float("nan") if wall is None else wall
    return float(timer.time_elapsed("train"))


def check_launcher(trainer: L.Trainer) -> None:
    """Lightning starts the other DDP processes by running this command again, which inside a Hydra multirun
    would run the whole sweep again in every process: refuse that (on SLURM, srun starts them instead)."""
    launcher = getattr(trainer.strategy, "launcher", None)
    if trainer.world_size <= 1 or launcher is None or not HydraConfig.initialized():
        return
    if HydraConfig.get().mode == RunMode.MULTIRUN:
        raise ValueError(
            f"{type(trainer.strategy).__name__} over {trainer.world_size} processes inside a multirun (-m): "
            "Lightning would start the whole sweep again in each process; train one run per command, or sweep on "
            "SLURM (hparams_search=slurm hydra.launcher.tasks_per_node=<trainer.devices>, docs/training.md)"
        )


def build_trainer(cfg: DictConfig, callbacks: list[L.Callback], logger: Any, run_dir: Path) -> L.Trainer:
    """The Lightning Trainer of cfg.trainer; settings Lightning refuses (e.g. trainer.accelerator=gpu on a machine
    without one) are one line, and so is DDP inside a local multirun."""
    try:
        trainer: L.Trainer = instantiate(cfg.trainer, callbacks=callbacks, logger=logger, default_root_dir=str(run_dir))
    except InstantiationException as e:
        reason = str(e.__cause__ or e).strip().splitlines()[0]
        where = ", ".join(
            f"trainer.{k}={cfg.trainer[k]}" for k in ("accelerator", "devices", "strategy") if k in cfg.trainer
        )
        raise ValueError(f"the trainer settings ({where}) were refused: {reason}") from None
    check_launcher(trainer)
    return trainer


def sha256(tensors: list[torch.Tensor]) -> str:
    """Checksum of the exact values (as float64) of some tensors, in order."""
    flat = torch.cat([t.detach().reshape(-1).cpu().double() for t in tensors])
    return hashlib.sha256(flat.numpy().tobytes()).hexdigest()


def ddp_record(trainer: L.Trainer, module: L.LightningModule, datamodule: L.LightningDataModule) -> dict[str, Any]:
    """Per process: its shard of points, redraws, stalls and a checksum of the parameters, gathered from every
    process (a collective: all of them call it); the proof that the processes trained on different points and
    kept identical parameters."""
    mine = {
        "rank": trainer.global_rank,
        "points": len(datamodule.batch["t"]),
        "points_sha256": sha256([datamodule.batch[k] for k in ("t", "x0", "u")]),
        "params_sha256": sha256(list(module.parameters())),
        "draws": int(datamodule.draws),
        "stalls": int(getattr(module, "stalls", 0)),
    }
    ranks: list[Any] = [None] * trainer.world_size
    torch.distributed.all_gather_object(ranks, mine)
    return {"strategy": type(trainer.strategy).__name__, "world_size": trainer.world_size, "ranks": ranks}


def resume_command(cfg_overrides: list[str], run_dir: Path) -> str:
    """The command that continues this run from its last.ckpt, to paste into a shell as printed: the overrides as
    Hydra got them, the run dir quoted for Hydra's grammar, the whole line for the shell."""
    skip = ("resume=", "ckpt_path=", "hydra.run.dir=", "+resume=", "+ckpt_path=")
    kept = [o for o in cfg_overrides if not o.startswith(skip)]
    words = ["python", "-m", "pinnmpc.train", *kept, "resume=true", override("hydra.run.dir", str(run_dir))]
    return command_line(words)


def anchor_count(cfg: DictConfig) -> int:
    """The anchors a run integrates: module.weight_anchor=0 switches them off, so none is spent on a term the loss
    ignores."""
    return 0 if cfg.module.get("weight_anchor") == 0 else int(cfg.data.get("n_anchor", 0))


def build_datamodule(cfg: DictConfig, system: System, physics: System | None = None) -> CollocationDataModule:
    """The run's training points, anchors of `physics` (the arm's own model by default); with model.command_delay
    the robot's pairs from that far into each period."""
    return instantiate(cfg.data, _partial_=True, _convert_="all")(
        system=system,
        tau=system.tau,
        t_max=cfg.t_max,
        seed=cfg.seed,
        n_anchor=anchor_count(cfg),
        physics=physics,
        robot_start=cfg.model.get("command_delay"),
    )


def train(
    cfg: DictConfig,
    run_dir: Path,
    command: str = "python -m pinnmpc.train",
    stop: StopSignal | None = None,
    overrides: list[str] | None = None,
) -> dict[str, Any]:
    """Fit, export the best network as surrogate.pt, and return its validation metrics; with a StopSignal, a
    SIGTERM/SIGINT ends training after the current (cut short) epoch with status "interrupted" and a resume command."""
    system: System = build_system(cfg.system)
    validate_train(cfg, system)
    if cfg.data.get("logs") and anchor_count(cfg) and not cfg.get("physics"):
        raise ValueError(
            f"data.n_anchor={cfg.data.n_anchor} with data.logs and physics=null: anchors of the nominal model would "
            "pull the fine-tuning towards the arm the robot is not; expected physics=<the .yaml of python -m "
            f"pinnmpc.identify system={system.name} logs=[...] out=...> or data.n_anchor=0"
        )
    physics, physics_meta, physics_arm = physics_model(cfg.get("physics"), system, cfg.get("physics_prior_slope"))
    previous = bool(cfg.model.get("previous_input"))
    if previous:  # the network takes the period before's input too; the logs give it, the physics ignore it
        plain, system = system, WithPreviousInput(system)
        physics = system if physics is plain else WithPreviousInput(physics)
    ckpt_path = resolve_ckpt(cfg, run_dir)
    label = f"ckpt_path={ckpt_path}" if cfg.ckpt_path else f"resume=true: {ckpt_path}"
    ckpt = None if ckpt_path is None else read_ckpt(ckpt_path, label)
    unfinished = ckpt is not None and cfg.resume and not cfg.ckpt_path and not (run_dir / "surrogate.pt").is_file()
    if unfinished and spent_budget(cfg, ckpt, label):  # killed after its budget but before it wrote its network
        return finish_spent_run(cfg, run_dir, ckpt, command)
    if ckpt is not None:
        check_continuable(cfg, ckpt, label)
    elif (run_dir / "checkpoints" / "last.ckpt").is_file():
        raise ValueError(
            f"hydra.run.dir={run_dir} holds a training run (checkpoints/last.ckpt); expected resume=true to continue "
            "it, or another run dir (a fresh run there would overwrite it)"
        )
    quiet_lightning()
    L.seed_everything(cfg.seed, workers=True, verbose=False)
    use_threads(cfg.threads)  # torch and numpy BLAS alike
    stored = (ckpt or {}).get("pinnmpc") or {}
    if ckpt is not None and cfg.get("init_from") and stored.get("model"):
        model = PINN(**stored["model"])  # resuming a widened network: its form is in the checkpoint, weights follow
    else:
        model = build_model(cfg, system, physics_arm)  # a frozen-arm prior holds the identified model still
    # _convert_="all": plain lists, not OmegaConf ones, reach the hyper-parameters stored in checkpoints,
    # which load_surrogate reads with torch.load(weights_only=True)
    datamodule = build_datamodule(cfg, system, physics)  # anchors of the same model as the residual
    module = instantiate(cfg.module, _partial_=True, _convert_="all")(system=physics, model=model, tau=system.tau)
    recorded = None
    if ckpt is not None:
        check_fits(ckpt, label, module)
        recorded = recorded_best(ckpt)
        del ckpt
    ckpt_dir = run_dir / "checkpoints"
    best = AtomicCheckpoint(dirpath=ckpt_dir, filename="best", monitor="val/rmse_position", mode="min")
    last = AtomicCheckpoint(  # every epoch, so a killed run loses at most one epoch of work
        dirpath=ckpt_dir, filename="last", every_n_epochs=1, save_on_train_epoch_end=True, enable_version_counter=False
    )
    figure = SelfLoopFigure(
        cfg.self_loop_figure.every_n_epochs, cfg.self_loop_figure.steps, cfg.self_loop_figure.amplitude
    )
    # a resumed run's earlier networks are counted in its checkpoint (the file they came from may be gone)
    recorded_base = stored.get("base_training_time_s")
    base_time = (
        recorded_base if recorded_base is not None else base_training_time(cfg.stage.base or cfg.get("init_from"))
    )
    callbacks: list[L.Callback] = [best, last, SurrogateFacts(system.tau, base_time), figure, BudgetBar(cfg.progress)]
    callbacks += [EpochLog(run_dir / "train.log", system.state_names), TrainingClock()]
    if cfg.trainer.get("max_time") is None:  # with max_time Lightning adds this Timer itself
        callbacks.append(Timer())  # counts training time across resumes (its state is in every checkpoint)
    if stop is not None:
        callbacks.append(GracefulStop(stop))
    logger = L.pytorch.loggers.TensorBoardLogger(save_dir=str(run_dir), name="tensorboard", version="")
    trainer = build_trainer(cfg, callbacks, logger, run_dir)
    if cfg.progress and trainer.is_global_zero:  # the set-up before the bar opens takes a while on large arms
        d = cfg.data
        print(
            f"pinnmpc.train: drawing {d.n_collocation} collocation points, integrating {d.n_anchor} anchors and "
            f"{d.n_val} validation steps by fine RK4; the bar opens when training starts",
            file=sys.stderr,
        )
    start, finished = time.perf_counter(), False
    try:
        trainer.fit(module, datamodule=datamodule, ckpt_path=ckpt_path)
        finished = True
    except (KeyboardInterrupt, SystemExit):  # a second signal: stop at once, keep the last epoch's checkpoint
        if stop is None or not stop.requested:
            raise
    wall = time.perf_counter() - start
    # DDP: every process that finished fit gathers the record (one stopped at once by a second signal does not)
    distributed = ddp_record(trainer, module, datamodule) if trainer.world_size > 1 and finished else None
    interrupted = stop is not None and stop.requested
    # this run dir's own checkpoints only: resumed from a copy of another run dir, Lightning keeps that dir's best path
    mine = ckpt_dir.resolve()
    own = [Path(p) for p in (best.best_model_path, last.best_model_path) if p and Path(p).resolve().parent == mine]
    fallback = [p for p in (ckpt_dir / "best.ckpt", ckpt_dir / "last.ckpt") if p.is_file()]
    source = str((own or fallback or [""])[0])
    meta = {
        "trained_with": command,
        "config": OmegaConf.to_container(cfg, resolve=True),
        "status": "interrupted" if interrupted else "ok",  # the same word as train_metrics.json and closed loops
        "wall_time_s": wall,
        # every network inside this one counts: a stage's frozen base or the network it started from too
        "training_time_s": training_time(trainer, wall) + base_time,
        "base_training_time_s": base_time,  # that part (where a curve of this run starts: pinnmpc.curves)
        "epochs": trainer.current_epoch,
        "best_val_rmse_position": float(best.best_model_score) if best.best_model_score is not None else None,
        "resumed_best_val_rmse_position": recorded,  # what the checkpoint resumed from had reached (None: fresh)
        "final_metrics": {k: float(v) for k, v in trainer.callback_metrics.items()},
    }
    if datamodule.robot_meta:  # a fine-tuned network: what it learnt from (system, robot, seed, noise, command)
        meta["robot_logs"] = datamodule.robot_meta
    if physics_meta is not None:  # the residual of a model identified from the logs, not the nominal arm's
        meta["physics"] = physics_meta
    if previous:  # its inputs are (u, u_prev): the controller feeds u_prev (pinnmpc.surrogate.previous_input)
        meta["previous_input"] = True
    if cfg.model.get("command_delay"):  # the controller splits each period there (pinnmpc.surrogate.delayed_command)
        meta["command_delay"] = float(cfg.model.command_delay)
    if interrupted and stop is not None:
        meta["signal"] = stop.name
    if distributed is not None:
        meta["distributed"] = distributed
    if not trainer.is_global_zero:  # DDP: rank 0 writes the run's files
        return {**meta, "best_checkpoint": source or None, "rank": trainer.global_rank}
    if recorded is not None and best.best_model_score is not None and float(best.best_model_score) > recorded:
        log.warning(  # Lightning keeps only the best path of a checkpoint from another directory, not its score
            "this run's best validation RMSE %.4g is above the %.4g recorded in the checkpoint it resumed from: "
            "surrogate.pt is this run's best, not that one (which stays in the run dir the checkpoint came from)",
            float(best.best_model_score),
            recorded,
        )
    if source and Path(source).is_file():
        surrogate = load_surrogate(source)
        surrogate.meta = meta
        surrogate.save(run_dir / "surrogate.pt")
    summary = {**meta, "best_checkpoint": source or None}
    summary.pop("config")
    if interrupted:
        resumable = (run_dir / "checkpoints" / "last.ckpt").is_file()
        summary["resume_command"] = resume_command(overrides or [], run_dir) if resumable else None
    save_json(run_dir / "train_metrics.json", summary)
    return summary


def train_command(cfg: DictConfig, run_dir: Path, **kwargs: Any) -> dict[str, Any]:
    """What `python -m pinnmpc.train` runs: one network, or with stage.split a base and a correction stage on it
    (kwargs: train's command, stop and overrides)."""
    resume = resume_command(kwargs.get("overrides") or [], run_dir)
    return train_in_stages(cfg, run_dir, lambda c, d: train(c, d, **kwargs), resume)
