"""What a training run shows on the terminal: the time budget and the validation error, nothing else.

Lightning's own bar counts epochs against max_epochs (a bound nobody reaches: max_time ends the run), and its
start-up prints advertisements and a model summary; a user wants to know how long it will run and how good the
network is so far.
"""

from __future__ import annotations

import logging
import sys
import warnings
from collections.abc import Sequence
from pathlib import Path

import lightning as L
from lightning.pytorch.callbacks import Timer
from tqdm.auto import tqdm

from pinnmpc.training.curves import CLOCK
from pinnmpc.training.pipeline import duration
from pinnmpc.util.io import append_log

NOISE = ("💡 Tip", "GPU available", "TPU available", "HPU available")  # Lightning start-up lines with no news


class _DropNoise(logging.Filter):
    """Logging filter that drops Lightning's start-up advertisements and hardware lines."""

    def filter(self, record: logging.LogRecord) -> bool:
        """Keep every record that does not start with one of NOISE."""
        return not str(record.getMessage()).startswith(NOISE)


def quiet_lightning() -> None:
    """Silence what carries no information for a pinnmpc user (kept in the logs of a verbose run)."""
    for name in ("lightning.pytorch.utilities.rank_zero", "lightning.fabric.utilities.rank_zero"):
        logging.getLogger(name).addFilter(_DropNoise())
    warnings.filterwarnings("ignore", message=".*LeafSpec.*")  # torch pytree deprecation inside Lightning


class BudgetBar(L.Callback):
    """A tqdm bar over the wall-time budget (trainer.max_time), with epoch, loss and validation RMSE."""

    def __init__(self, enabled: bool = True) -> None:
        self.enabled = enabled
        self.bar: tqdm | None = None

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """Open the bar at the time already spent (a resumed run starts part-way)."""
        timer = timer_of(trainer)
        if not self.enabled or timer is None or not trainer.is_global_zero:
            return
        total = float(timer._duration or 0.0)
        self.bar = tqdm(
            total=round(total),
            initial=round(timer.time_elapsed("train")),
            desc="training",
            unit="s",
            file=sys.stderr,
            bar_format="{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} s [{elapsed}<{remaining}]{postfix}",
            dynamic_ncols=True,
        )

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """Advance to the elapsed time and show the latest numbers."""
        timer = timer_of(trainer)
        if self.bar is None or timer is None:
            return
        done = min(round(timer.time_elapsed("train")), self.bar.total)  # the last epoch may overrun the budget
        self.bar.update(max(0, done - self.bar.n))
        m = trainer.callback_metrics
        post = {"epoch": trainer.current_epoch}
        for key, label in (
            ("train/loss_total", "loss"),
            ("val/rmse_position", "val q"),
            ("val/rmse_velocity", "val v"),
        ):
            if key in m:
                post[label] = f"{float(m[key]):.2e}"
        self.bar.set_postfix(post, refresh=True)

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """Close the bar so the summary line prints below it."""
        if self.bar is not None:
            self.bar.close()
            self.bar = None


class EpochLog(L.Callback):
    """One line per epoch in the run dir's train.log (loss, validation RMSE per state, training time), written
    to the file only: the terminal has the bar, the log keeps the history a killed or remote run leaves behind."""

    def __init__(self, path: Path, state_names: Sequence[str]) -> None:
        self.path = path
        self.state_names = list(state_names)

    def _write(self, trainer: L.Trainer, message: str) -> None:
        """Append to train.log (rank 0 only: the other DDP processes share the run dir)."""
        if trainer.is_global_zero:
            append_log(self.path, message)

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """Say what runs."""
        params = sum(p.numel() for p in pl_module.parameters() if p.requires_grad)
        optimizer = pl_module.hparams.get("optimizer", "lbfgs")
        self._write(
            trainer,
            f"training from epoch {trainer.current_epoch}: optimizer {optimizer}, {params} parameters, "
            f"budget {_budget(trainer)}",
        )

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """Loss, validation RMSE per state (when this epoch validated) and training time so far."""
        m = trainer.callback_metrics
        timer = timer_of(trainer)
        elapsed = f"{timer.time_elapsed('train'):.0f} s" if timer is not None else "?"
        val = " ".join(f"{n}={float(m[f'val/rmse_{n}']):.3e}" for n in self.state_names if f"val/rmse_{n}" in m)
        loss = f"{float(m['train/loss_total']):.3e}" if "train/loss_total" in m else "?"
        self._write(trainer, f"epoch {trainer.current_epoch}  time {elapsed}  loss {loss}  val rmse {val or '-'}")

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """Say where training ended."""
        done = trainer.current_epoch  # Lightning counts an epoch once it ends: the last one run is done - 1
        self._write(trainer, f"training ended after epoch {done - 1}" if done else "training ended before epoch 0 did")

    def on_exception(self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException) -> None:
        """Say how the run ended."""
        self._write(trainer, f"stopped by {type(exception).__name__}: {exception}")


class TrainingClock(L.Callback):
    """Logs the training time so far (Lightning's Timer, resumes included, set-up excluded) beside each validation,
    so `pinnmpc.curves` plots accuracy against what training cost, not against wall time since the logger began."""

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """Log time/train_s at the validation's step."""
        timer = timer_of(trainer)
        if timer is not None and not trainer.sanity_checking:
            pl_module.log(CLOCK, float(timer.time_elapsed("train")), batch_size=1, sync_dist=False, rank_zero_only=True)


def timer_of(trainer: L.Trainer) -> Timer | None:
    """Lightning's Timer (added whenever max_time is set): training time across resumes and the budget."""
    return next((c for c in trainer.callbacks if isinstance(c, Timer)), None)


def _budget(trainer: L.Trainer) -> str:
    """The wall-time budget Lightning's Timer holds, as DD:HH:MM:SS, or 'none'."""
    timer = timer_of(trainer)
    return duration(float(timer._duration)) if timer is not None and timer._duration else "none"
