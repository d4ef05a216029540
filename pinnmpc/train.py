"""`python -m pinnmpc.train [overrides]`: train a PINN surrogate; outputs go to the Hydra run dir."""

from __future__ import annotations

import hashlib
import shlex
import sys
import time
from pathlib import Path
from typing import Any

import hydra
import lightning as L
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.errors import InstantiationException
from hydra.types import RunMode
from hydra.utils import instantiate
from lightning.pytorch.callbacks import Timer
from omegaconf import DictConfig, OmegaConf

from pinnmpc.cli import StopSignal, check_choices, config_dir_args, run_cli, say
from pinnmpc.surrogate.checkpoint import FORMAT, load_surrogate
from pinnmpc.surrogate.network import PINN
from pinnmpc.surrogate.prior import FrozenArmPrior
from pinnmpc.surrogate.staged import StagedPINN
from pinnmpc.systems.base import System
from pinnmpc.systems.registry import build_system
from pinnmpc.training.callbacks import AtomicCheckpoint, GracefulStop, SelfLoopFigure, SurrogateFacts
from pinnmpc.training.data import CollocationDataModule, flow_scale
from pinnmpc.training.grow import grown_model
from pinnmpc.training.pipeline import base_training_time, seconds, train_in_stages
from pinnmpc.training.progress import BudgetBar, EpochLog, TrainingClock, quiet_lightning, timer_of
from pinnmpc.training.stage import staged_model
from pinnmpc.util.io import save_json
from pinnmpc.util.settings import validate_train
from pinnmpc.util.threads import use_threads


def build_model(cfg: DictConfig, system: System) -> PINN | StagedPINN:
    """The network for this system's training box (output scale estimated from the flow when 'auto'), or with
    stage.base a correction network on top of that trained one, or with init_from that one widened to model.hidden."""
    if cfg.stage.base:
        return build_staged(cfg, system)
    if cfg.get("init_from"):
        hidden, basis, sums = list(cfg.model.hidden), list(cfg.model.time_basis), _angle_sums(cfg)
        prior = cfg.model.get("prior")
        keys = ("activation", "ic", "second_order", "periodic")
        form = {
            k: OmegaConf.to_object(v) if OmegaConf.is_config(v) else v
            for k in keys
            if (v := cfg.model.get(k)) is not None
        }
        return grown_model(system, cfg.init_from, cfg.tau, cfg.t_max, hidden, cfg.seed, basis, sums, prior, form)
    return fresh_model(cfg, system)


def fresh_model(cfg: DictConfig, system: System) -> PINN:
    """A new network of cfg.model for this system's training box (output scale estimated from the flow when
    'auto'): what training and the capacity check start from."""
    kind = cfg.model.get("prior")
    # the arm's own description travels with the network: a user's arm outside conf/system, or one whose name a
    # shipped arm shares, rebuilds the same prior wherever the network is loaded
    dynamics = OmegaConf.to_container(cfg.system.dynamics, resolve=True) if "dynamics" in cfg.system else None
    if dynamics is not None and getattr(system, "urdf", None):  # the file the arm was built from, found anywhere
        from pinnmpc.systems.urdf import portable_urdf

        dynamics["urdf"] = portable_urdf(system.urdf)
    prior = None if kind is None else {"kind": str(kind), "system": system.name, "dynamics": dynamics}
    scale = cfg.model.output_scale
    if scale == "auto":
        a = cfg.model.auto_scale
        start = None if prior is None else FrozenArmPrior(system)
        scale = flow_scale(system, cfg.t_max, a.samples, a.h, a.quantile, cfg.seed, start)
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
        angle_sums=_angle_sums(cfg),
        prior=prior,
    )


def _angle_sums(cfg: DictConfig) -> list[list[int]]:
    """model.angle_sums as plain lists (none when the model config predates the setting)."""
    return [list(c) for c in cfg.model.get("angle_sums") or []]


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


LIGHTNING_KEYS = ("pytorch-lightning_version", "state_dict", "optimizer_states", "loops", "epoch", "global_step")
EXPECTED_CKPT = "expected a Lightning .ckpt written by pinnmpc.train (e.g. <run dir>/checkpoints/last.ckpt)"


def training_time(trainer: L.Trainer, wall: float | None = None) -> float:
    """Training time across processes: the Timer (train() always has one) starts from what the checkpoint it
    resumed from had counted; the time a killed process spent after its last checkpoint is not in it."""
    timer = timer_of(trainer)
    if timer is None:
        return float("nan") if wall is None else wall
    return float(timer.time_elapsed("train"))


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


def check_continuable(cfg: DictConfig, ckpt: dict[str, Any], label: str) -> None:
    """A checkpoint this configuration can train on: the same optimizer (its state is restored), and budget left
    (a spent trainer.max_time or max_epochs runs no epoch and would rewrite the run's results from nothing)."""
    have, want = (ckpt.get("hyper_parameters") or {}).get("optimizer"), cfg.module.get("optimizer")
    if have is not None and have != want:
        raise ValueError(
            f"{label} was trained with module.optimizer={have}, this configuration has module.optimizer={want}; "
            "expected the same (its optimizer state is restored, as far as it is saved), or "
            "init_from=<its surrogate.pt> to start anew"
        )
    spent = ((ckpt.get("callbacks") or {}).get("Timer") or {}).get("time_elapsed", {}).get("train")
    budget = cfg.trainer.get("max_time")
    if budget and spent is not None and spent >= seconds(str(budget)):
        raise ValueError(
            f"{label} has trained {spent / 60:.1f} min, so trainer.max_time={budget} is spent; expected a longer "
            "trainer.max_time to continue"
        )
    limit, done = cfg.trainer.get("max_epochs"), int(ckpt.get("epoch", -1)) + 1
    if limit is not None and limit != -1 and done >= limit:
        raise ValueError(
            f"{label} has trained {done} epochs, so trainer.max_epochs={limit} is reached; expected a larger "
            "trainer.max_epochs to continue"
        )


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
    """The command that continues this run from its last.ckpt."""
    skip = ("resume=", "ckpt_path=", "hydra.run.dir=", "+resume=", "+ckpt_path=")
    kept = [o for o in cfg_overrides if not o.startswith(skip)]
    return shlex.join(["python", "-m", "pinnmpc.train", *kept, "resume=true", f"hydra.run.dir={run_dir}"])


def build_datamodule(cfg: DictConfig, system: System) -> CollocationDataModule:
    """The run's training points; module.weight_anchor=0 also switches the anchors off, so no integration is spent
    on a term the loss ignores."""
    n_anchor = 0 if cfg.module.get("weight_anchor") == 0 else cfg.data.get("n_anchor", 0)
    return instantiate(cfg.data, _partial_=True, _convert_="all")(
        system=system, tau=cfg.tau, t_max=cfg.t_max, seed=cfg.seed, n_anchor=n_anchor
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
    ckpt_path = resolve_ckpt(cfg, run_dir)
    label = f"ckpt_path={ckpt_path}" if cfg.ckpt_path else f"resume=true: {ckpt_path}"
    ckpt = None if ckpt_path is None else read_ckpt(ckpt_path, label)
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
        model = build_model(cfg, system)
    # _convert_="all": plain lists, not OmegaConf ones, reach the hyper-parameters stored in checkpoints,
    # which load_surrogate reads with torch.load(weights_only=True)
    datamodule = build_datamodule(cfg, system)
    module = instantiate(cfg.module, _partial_=True, _convert_="all")(system=system, model=model, tau=cfg.tau)
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
    callbacks: list[L.Callback] = [best, last, SurrogateFacts(cfg.tau, base_time), figure, BudgetBar(cfg.progress)]
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
    if interrupted and stop is not None:
        meta["signal"] = stop.name
    if distributed is not None:
        meta["distributed"] = distributed
    if not trainer.is_global_zero:  # DDP: rank 0 writes the run's files
        return {**meta, "best_checkpoint": source or None, "rank": trainer.global_rank}
    if recorded is not None and best.best_model_score is not None and float(best.best_model_score) > recorded:
        say(  # Lightning keeps only the best path of a checkpoint from another directory, not its score
            f"warning: this run's best validation RMSE {float(best.best_model_score):.4g} is above the {recorded:.4g} "
            "recorded in the checkpoint it resumed from: surrogate.pt is this run's best, not that one (which "
            "stays in the run dir the checkpoint came from)",
            run_dir,
            "pinnmpc.train",
            err=True,
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


@hydra.main(version_base="1.3", config_path="../conf", config_name="train")
def main(cfg: DictConfig) -> float:
    """CLI: returns the best validation position RMSE, so Optuna sweeps can minimise it."""
    hydra_cfg = hydra.core.hydra_config.HydraConfig.get()
    run_dir = Path(hydra_cfg.runtime.output_dir)
    overrides = [*config_dir_args(), *hydra_cfg.overrides.task]  # a user's own config dir travels along
    command = " ".join(["python -m pinnmpc.train", *overrides])
    with StopSignal() as stop:
        run = lambda: train_command(cfg, run_dir, command=command, stop=stop, overrides=overrides)  # noqa: E731
        summary = run_cli(run, "pinnmpc.train", run_dir)
    score = summary["best_val_rmse_position"]
    if summary.get("rank", 0) > 0:  # a DDP process of rank > 0: rank 0 reports
        return float("inf") if score is None else score
    if summary["status"] == "interrupted":
        exit_interrupted(summary, run_dir, stop)
    if score is None:  # the run ended before its first validation epoch
        every = cfg.trainer.check_val_every_n_epoch
        print(f"no validation ran (trainer.check_val_every_n_epoch={every}); outputs in {run_dir}")
        return float("inf")
    say(f"best val RMSE (positions) {score:.3e} rad; surrogate: {run_dir / 'surrogate.pt'}", run_dir, "pinnmpc.train")
    return score


def exit_interrupted(summary: dict[str, Any], run_dir: Path, stop: StopSignal) -> None:
    """Say what was kept and how to go on, then exit 128 + the signal number."""
    kept = ", ".join(
        n for n in ("checkpoints/last.ckpt", "surrogate.pt", "train_metrics.json") if (run_dir / n).is_file()
    )
    print(
        f"pinnmpc.train: interrupted by {stop.name} after {summary['epochs']} epochs; kept in {run_dir}: {kept}",
        file=sys.stderr,
    )
    if summary["resume_command"]:
        print(f"resume with: {summary['resume_command']}", file=sys.stderr)
    else:
        print("nothing to resume: no epoch had ended; start the run again", file=sys.stderr)
    sys.exit(stop.exit_code)


if __name__ == "__main__":
    check_choices("pinnmpc.train")
    main()
