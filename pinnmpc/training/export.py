"""Checkpoint hooks that keep training runs loadable as surrogates without Lightning."""

from __future__ import annotations

from typing import Any

import lightning as L


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
