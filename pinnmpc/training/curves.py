"""Training curves from a run's TensorBoard/CSV log: validation RMSE against training time, comparable across runs."""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pinnmpc.util.io import atomic_write

POSITION, VELOCITY = "val/rmse_position", "val/rmse_velocity"

CLOCK = "time/train_s"  # training time at each validation, logged by pinnmpc.training.progress.TrainingClock
MAX_GAP_S = 600.0  # a pause longer than this between two logged epochs is a resume, not training


@dataclass
class Curve:
    """One run's validation RMSE (worst position, worst velocity) against training minutes."""

    label: str
    minutes: np.ndarray
    position: np.ndarray
    velocity: np.ndarray


def read_curve(run_dir: Path, label: str | None = None) -> Curve:
    """The validation curve of one training run dir (an error naming the dir when it has no validation yet)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    tb = run_dir / "tensorboard"
    if not run_dir.is_dir():
        raise FileNotFoundError(f"{run_dir} does not exist; expected a pinnmpc.train run dir")
    if not tb.is_dir():
        raise FileNotFoundError(f"{run_dir} has no tensorboard/ folder; expected a pinnmpc.train run dir")
    acc = EventAccumulator(str(tb), size_guidance={"scalars": 0})
    acc.Reload()
    tags = acc.Tags()["scalars"]
    if POSITION not in tags:
        raise ValueError(f"{run_dir} has logged no validation yet ({POSITION}); let it run a few epochs")
    pos, vel = acc.Scalars(POSITION), acc.Scalars(VELOCITY)
    clock = {e.step: e.value for e in acc.Scalars(CLOCK)} if CLOCK in tags else {}
    if all(e.step in clock for e in pos):
        elapsed = np.array([clock[e.step] for e in pos])
    else:  # a run from before the clock: wall time since the logger began, long pauses (resumes) left out
        stamps = np.array([acc.FirstEventTimestamp(), *(e.wall_time for e in pos)])
        gaps = np.diff(stamps)
        elapsed = np.cumsum(np.where(gaps > MAX_GAP_S, 0.0, gaps))
    return Curve(
        label or run_dir.name,
        (elapsed + _base_seconds(run_dir)) / 60.0,
        np.array([e.value for e in pos]),
        np.array([e.value for e in vel]),
    )


def _base_seconds(run_dir: Path) -> float:
    """Training time behind the network a run started from (init_from, a stage's base): where its curve begins."""
    metrics = run_dir / "train_metrics.json"
    if not metrics.is_file():
        return 0.0
    return float(json.loads(metrics.read_text()).get("base_training_time_s") or 0.0)


def plot_curves(curves: list[Curve], out: Path, title: str = "") -> None:
    """Two log-scale panels (positions, velocities) against training minutes, one line per run."""
    from matplotlib.figure import Figure

    from pinnmpc.util.plots import save_figure

    fig = Figure(figsize=(11, 4), layout="constrained")
    axes = fig.subplots(1, 2, sharex=True)
    for c in curves:
        axes[0].semilogy(c.minutes, c.position, marker=".", label=c.label)
        axes[1].semilogy(c.minutes, c.velocity, marker=".", label=c.label)
    axes[0].set_ylabel("one-step RMSE, worst joint angle [rad]")
    axes[1].set_ylabel("one-step RMSE, worst joint velocity [rad/s]")
    for ax in axes:
        ax.set_xlabel("training wall time [min]")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=8)
    if title:
        fig.suptitle(title)
    save_figure(fig, out)


def write_csv(curves: list[Curve], out: Path) -> None:
    """The plotted points, one row per run and validation."""

    def write(p: Path) -> None:
        with p.open("w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["run", "minutes", "rmse_position", "rmse_velocity"])
            for c in curves:
                w.writerows(
                    [c.label, f"{m:.3f}", f"{p_:.4e}", f"{v:.4e}"]
                    for m, p_, v in zip(c.minutes, c.position, c.velocity)
                )

    atomic_write(out, write)
