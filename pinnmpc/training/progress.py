"""What a training run shows on the terminal: the time budget and the validation error, nothing else.

Lightning's own bar counts epochs against max_epochs (a bound nobody reaches: max_time ends the run), and its
start-up prints advertisements and a model summary; a user wants to know how long it will run and how good the
network is so far.
"""

from __future__ import annotations

import logging
import sys
import warnings

import lightning as L
from lightning.pytorch.callbacks import Timer
from tqdm.auto import tqdm

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

    def _timer(self, trainer: L.Trainer) -> Timer | None:
        """Lightning's Timer (added whenever max_time is set): elapsed time across resumes and the budget."""
        return next((c for c in trainer.callbacks if isinstance(c, Timer)), None)

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """Open the bar at the time already spent (a resumed run starts part-way)."""
        timer = self._timer(trainer)
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
        timer = self._timer(trainer)
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
