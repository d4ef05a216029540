"""`python -m pinnmpc.train [overrides]`: train a PINN surrogate; outputs go to the Hydra run dir."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig

from pinnmpc.cli import StopSignal, check_choices, config_dir_args, exit_stopped, run_cli, say

STOP = StopSignal()  # taken over from the command's first moment: a signal during start-up stops at the first epoch
_FIRST_JOB = [True]  # emptied once the process's first job has taken STOP


def job_stop() -> StopSignal:
    """The StopSignal of this job: STOP for the process's first job (a signal during start-up counts there), a
    fresh one for each later job of a sweep, as each job's own run."""
    if _FIRST_JOB:
        _FIRST_JOB.clear()
        return STOP
    return StopSignal()


@hydra.main(version_base="1.3", config_path="../conf", config_name="train")
def main(cfg: DictConfig) -> float:
    """CLI: returns the best validation position RMSE, so Optuna sweeps can minimise it."""
    # imported here: --help and a refused setting answer before torch loads
    from pinnmpc.training.run import train_command

    hydra_cfg = hydra.core.hydra_config.HydraConfig.get()
    run_dir = Path(hydra_cfg.runtime.output_dir)
    overrides = [*config_dir_args(), *hydra_cfg.overrides.task]  # a user's own config dir travels along
    command = " ".join(["python -m pinnmpc.train", *overrides])
    with job_stop() as stop:
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
    targets = target_note(summary.get("final_metrics", {}), cfg)
    say(
        f"best val RMSE (positions) {score:.3e} rad{targets}; surrogate: {run_dir / 'surrogate.pt'}",
        run_dir,
        "pinnmpc.train",
    )
    return score


def target_note(metrics: dict[str, float], cfg: DictConfig) -> str:
    """Whether the last validation met the system's one-step targets (system.targets.one_step_rmse), state by state:
    the question a training run answers; on the robot's held-out transitions when it fine-tuned on logs."""
    targets = (cfg.system.get("targets") or {}).get("one_step_rmse")
    if not targets:
        return ""
    # the validation logs one RMSE per state in state order, then the position and velocity maxima
    vals = {k.removeprefix("val/rmse_"): v for k, v in metrics.items() if k.startswith("val/rmse_")}
    vals = {k: v for k, v in vals.items() if k not in ("position", "velocity")}
    pairs = [(n, v, t) for (n, v), t in zip(vals.items(), targets) if t is not None]
    if not pairs:
        return ""
    where = " on the robot's held-out transitions" if cfg.data.get("logs") else ""
    missed = [f"{n} {v / t:.2g}x" for n, v, t in pairs if v > t]
    if not missed:
        return f"; one-step targets met in every state{where} (last validation)"
    return f"; one-step targets missed{where} (last validation): {', '.join(missed)}"


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
    exit_stopped(stop.exit_code, f"interrupted by {stop.name}", run_dir)


if __name__ == "__main__":
    STOP.install()  # before Hydra composes and torch loads: a signal from here on leaves a checkpoint to resume
    check_choices("pinnmpc.train")
    main()
