"""Training callbacks: atomic checkpoints, the facts that make them loadable as surrogates, a self-loop figure,
a clean stop on SIGTERM/SIGINT."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any
from weakref import proxy

import lightning as L
import numpy as np
import torch
from lightning.pytorch.callbacks import ModelCheckpoint

from pinnmpc.cli import StopSignal
from pinnmpc.io import atomic_write
from pinnmpc.plant import ScipyPlant
from pinnmpc.training.ssbfgs import SSBFGS


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

    def __init__(self, every_n_epochs: int, steps: int, amplitude: Sequence[float]) -> None:
        self.every_n_epochs, self.steps, self.amplitude = int(every_n_epochs), int(steps), list(amplitude)
        self.reference: dict[str, np.ndarray] = {}

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """The plant side of the test is fixed: compute it once."""
        from pinnmpc.self_loop import rollout_plant, sine_inputs

        if self.every_n_epochs <= 0:
            return
        u = sine_inputs(self.steps, self.amplitude)
        box = pl_module.system.state_box
        x0 = (np.array(box.low) + np.array(box.high)) / 2  # the middle of the training box, at rest
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
        xs = [torch.as_tensor(self.reference["x"][0], dtype=u.dtype)]
        with torch.no_grad():
            for uk in u:
                xs.append(model(torch.full((1,), pl_module.tau, dtype=u.dtype), xs[-1], uk))
        x_pinn = torch.stack(xs).double().numpy()
        t = pl_module.tau * np.arange(len(u) + 1)
        fig = plots.self_loop_figure(
            t,
            self.reference["x"],
            x_pinn,
            self.reference["u"],
            plots.Labels.of(pl_module.system),
            title=f"epoch {trainer.current_epoch}",
        )
        experiment.add_figure("self_loop", fig, global_step=trainer.global_step)


class GracefulStop(L.Callback):
    """On SIGTERM/SIGINT (a StopSignal): end training after the current epoch, cutting its L-BFGS call short, so
    the epoch-end checkpoint is written and the run resumes from it (Lightning's own SIGTERM path exits 0 mid-epoch
    without a checkpoint)."""

    def __init__(self, stop: StopSignal) -> None:
        self.stop = stop
        self._wrapped: list[torch.optim.Optimizer] = []

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """Take the signals back from Lightning (it restores ours at teardown), and guard the L-BFGS closures."""
        self.stop.hooks.append(lambda: setattr(trainer, "should_stop", True))
        self.stop.install()
        if self.stop.requested:  # the signal came during setup
            trainer.should_stop = True
        for opt in trainer.optimizers:
            inner = getattr(opt, "optimizer", opt)
            if isinstance(inner, torch.optim.LBFGS | SSBFGS):
                inner.step = self._guarded_step(inner)  # type: ignore[method-assign]
                self._wrapped.append(inner)

    def _guarded_step(self, opt: torch.optim.Optimizer) -> Any:
        """L-BFGS's step whose closure reports a zero gradient once a stop is asked for: the line search then
        accepts its next point of sufficient decrease and the gradient test ends the call, so the network stops
        at a point L-BFGS accepted (the true gradient of the next start keeps the history consistent)."""
        step = opt.step

        def guarded(closure: Any = None) -> Any:
            if closure is None:
                return step()

            def closure_checked() -> Any:
                loss = closure()
                if self.stop.requested:
                    for group in opt.param_groups:
                        for p in group["params"]:
                            if p.grad is not None:
                                p.grad.zero_()
                return loss

            return step(closure_checked)

        return guarded

    def _unwrap(self) -> None:
        """Leave the optimizers as they were."""
        for opt in self._wrapped:
            opt.__dict__.pop("step", None)
        self._wrapped = []

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """Training is over."""
        self._unwrap()

    def on_exception(self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException) -> None:
        """Training ended in an error."""
        self._unwrap()
