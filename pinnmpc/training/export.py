"""Checkpoint callbacks: atomic writes, and the facts that make a training checkpoint loadable as a surrogate."""

from __future__ import annotations

from typing import Any
from weakref import proxy

import lightning as L
from lightning.pytorch.callbacks import ModelCheckpoint

from pinnmpc.io import atomic_write


class AtomicCheckpoint(ModelCheckpoint):
    """ModelCheckpoint whose files appear whole or not at all: a killed run never leaves a truncated .ckpt."""

    def _save_checkpoint(self, trainer: L.Trainer, filepath: str) -> None:
        """Lightning's save, through a temporary file and a rename."""
        atomic_write(filepath, lambda tmp: trainer.save_checkpoint(str(tmp), self.save_weights_only), suffix=".ckpt")
        self._last_global_step_saved = trainer.global_step
        self._last_checkpoint_saved = filepath
        if trainer.is_global_zero:
            for logger in trainer.loggers:
                logger.after_save_checkpoint(proxy(self))


class SurrogateFacts(L.Callback):
    """Store the network config and system facts inside every Lightning checkpoint."""

    def __init__(self, tau: float) -> None:
        self.tau = float(tau)

    def on_save_checkpoint(self, trainer: L.Trainer, pl_module: L.LightningModule, checkpoint: dict[str, Any]) -> None:
        """Add what load_surrogate needs next to Lightning's own keys."""
        system = pl_module.system
        checkpoint["pinnmpc"] = {
            "version": 1,
            "tau": self.tau,
            "state_names": list(system.state_names),
            "input_names": list(system.input_names),
            "model": pl_module.model.config,
        }
