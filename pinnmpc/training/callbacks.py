"""Training callbacks: atomic checkpoints, the facts that make them loadable as surrogates, a self-loop figure."""

from __future__ import annotations

from typing import Any
from weakref import proxy

import lightning as L
import numpy as np
import torch
from lightning.pytorch.callbacks import ModelCheckpoint

from pinnmpc.io import atomic_write
from pinnmpc.plant import ScipyPlant


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


class SelfLoopFigure(L.Callback):
    """Every N epochs, the paper's self-loop test as a TensorBoard figure: the picture of how training is going."""

    def __init__(self, every_n_epochs: int, steps: int, amplitude: float) -> None:
        self.every_n_epochs, self.steps, self.amplitude = int(every_n_epochs), int(steps), float(amplitude)
        self.reference: dict[str, np.ndarray] = {}

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """The plant side of the test is fixed: compute it once."""
        from pinnmpc.self_loop import rollout_plant, sine_inputs

        if self.every_n_epochs <= 0:
            return
        u = sine_inputs(self.steps, self.amplitude)
        x0 = np.zeros(len(pl_module.system.state_names))
        self.reference = {"u": u, "x": rollout_plant(ScipyPlant(pl_module.system, pl_module.tau), x0, u)}

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """Roll the current network out and log the figure."""
        from pinnmpc import plots

        if self.every_n_epochs <= 0 or (trainer.current_epoch + 1) % self.every_n_epochs or trainer.logger is None:
            return
        experiment = getattr(trainer.logger, "experiment", None)
        if not hasattr(experiment, "add_figure"):
            return
        model, u = pl_module.model, torch.as_tensor(self.reference["u"], dtype=pl_module.res_scale.dtype)
        xs = [torch.zeros(model.nx, dtype=u.dtype)]
        with torch.no_grad():
            for uk in u:
                xs.append(model(torch.full((1,), pl_module.tau, dtype=u.dtype), xs[-1], uk))
        x_pinn = torch.stack(xs).double().numpy()
        t = pl_module.tau * np.arange(len(u) + 1)
        fig = plots.self_loop_figure(
            t, self.reference["x"], x_pinn, self.reference["u"], title=f"epoch {trainer.current_epoch}"
        )
        experiment.add_figure("self_loop", fig, global_step=trainer.global_step)
