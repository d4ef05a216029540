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

from pinnmpc.plant.scipy_plant import ScipyPlant
from pinnmpc.systems.previous_input import arm_system, with_previous
from pinnmpc.training.ssbfgs import SSBFGS
from pinnmpc.util.io import atomic_write
from pinnmpc.util.signals import StopSignal


class AtomicCheckpoint(ModelCheckpoint):
    """ModelCheckpoint whose files appear whole or not at all: a killed run never leaves a truncated .ckpt."""

    def _save_checkpoint(self, trainer: L.Trainer, filepath: str) -> None:
        """Lightning's save, through a temporary file and a rename by the process that writes (global rank 0; the
        other DDP processes take part in the save, which writes nothing there, and must not rename)."""
        if trainer.is_global_zero:
            atomic_write(
                filepath, lambda tmp: trainer.save_checkpoint(str(tmp), self.save_weights_only), suffix=".ckpt"
            )
        else:
            trainer.save_checkpoint(filepath, self.save_weights_only)
        self._last_global_step_saved = trainer.global_step
        self._last_checkpoint_saved = filepath
        if trainer.is_global_zero:
            for logger in trainer.loggers:
                logger.after_save_checkpoint(proxy(self))


class SurrogateFacts(L.Callback):
    """Store the network config and system facts inside every Lightning checkpoint."""

    def __init__(self, tau: float, base_training_time_s: float = 0.0) -> None:
        self.tau = float(tau)
        self.base_training_time_s = float(base_training_time_s)  # the network it started from, for later runs

    def on_save_checkpoint(self, trainer: L.Trainer, pl_module: L.LightningModule, checkpoint: dict[str, Any]) -> None:
        """Add what load_surrogate needs next to Lightning's own keys."""
        system = pl_module.system
        checkpoint["pinnmpc"] = {
            "version": 1,
            "tau": self.tau,
            "state_names": list(system.state_names),
            "input_names": list(system.input_names),
            "model": pl_module.model.config,
            "base_training_time_s": self.base_training_time_s,
        }


class SelfLoopFigure(L.Callback):
    """Every N epochs, the paper's self-loop test as a TensorBoard figure: the picture of how training is going."""

    def __init__(self, every_n_epochs: int, steps: int, amplitude: Sequence[float]) -> None:
        self.every_n_epochs, self.steps, self.amplitude = int(every_n_epochs), int(steps), list(amplitude)
        self.reference: dict[str, np.ndarray] = {}

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """The plant side of the test is fixed: compute it once (on the process that logs)."""
        from pinnmpc.simulation.self_loop import rollout_plant, sine_inputs

        if self.every_n_epochs <= 0 or not trainer.is_global_zero:
            return
        u = sine_inputs(self.steps, self.amplitude)
        box = pl_module.system.state_box
        x0 = (np.array(box.low) + np.array(box.high)) / 2  # the middle of the training box, at rest
        self.reference = {"u": u, "x": rollout_plant(ScipyPlant(pl_module.system, pl_module.tau), x0, u)}

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """Roll the current network out and log the figure."""
        from pinnmpc.util import plots

        if self.every_n_epochs <= 0 or (trainer.current_epoch + 1) % self.every_n_epochs or trainer.logger is None:
            return
        if not trainer.is_global_zero:
            return
        experiment = getattr(trainer.logger, "experiment", None)
        if not hasattr(experiment, "add_figure"):
            return
        like = pl_module.res_scale
        model, u = pl_module.model, torch.as_tensor(self.reference["u"], dtype=like.dtype, device=like.device)
        xs = [torch.as_tensor(self.reference["x"][0], dtype=u.dtype, device=u.device)]
        inputs = with_previous(u) if model.nu > u.shape[-1] else u  # a network given the previous input too
        with torch.no_grad():
            for uk in inputs:
                xs.append(model(torch.full((1,), pl_module.tau, dtype=u.dtype, device=u.device), xs[-1], uk))
        x_pinn = torch.stack(xs).double().cpu().numpy()
        t = pl_module.tau * np.arange(len(u) + 1)
        fig = plots.self_loop_figure(
            t,
            self.reference["x"],
            x_pinn,
            self.reference["u"],
            plots.Labels.of(arm_system(pl_module.system)),  # the arm's inputs, not u_prev
            title=f"epoch {trainer.current_epoch}",
        )
        experiment.add_figure("self_loop", fig, global_step=trainer.global_step)


class GracefulStop(L.Callback):
    """On SIGTERM/SIGINT (a StopSignal): end training after the current epoch, cutting its L-BFGS call short, so
    the epoch-end checkpoint is written and the run resumes from it (Lightning's own SIGTERM path exits 0 mid-epoch
    without a checkpoint). A signal before the first epoch's step (during start-up, setup, or between the start of
    training and that step) runs that epoch cut short from its first loss evaluation: a run stopped at any moment
    leaves a checkpoint to resume from. The stop is asked for only once the epoch has stepped (trainer.should_stop
    set earlier would end the run before any step, with no checkpoint). Under DDP a signal may reach one process
    only (`kill` of rank 0): every process asks all the others at each loss evaluation and each epoch end, so they
    cut the same L-BFGS call short and stop together."""

    def __init__(self, stop: StopSignal) -> None:
        self.stop = stop
        self._wrapped: list[torch.optim.Optimizer] = []

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """Take the signals back from Lightning (it restores ours at teardown), and guard the L-BFGS closures."""
        self.stop.install()
        connector = getattr(trainer, "_signal_connector", None)
        if self.stop.requested and connector is not None and connector.received_sigterm:
            # a SIGTERM between Lightning's taking the signals and this hook reached its handler and ours: ours ends
            # the run after its first (cut short) epoch, as at any other moment; Lightning's flag would end it in a
            # SIGTERMException instead, past on_train_end (and under DDP before that epoch's step: no checkpoint)
            connector.received_sigterm = False
        # a signal does not set trainer.should_stop here (nor from the signal handler): with it set before the
        # epoch's first step Lightning ends the run without an epoch, so without the checkpoint a resume needs.
        # The epoch runs, cut short at once, and on_train_batch_end / on_train_epoch_end stop after it
        for opt in trainer.optimizers:
            inner = getattr(opt, "optimizer", opt)
            if isinstance(inner, torch.optim.LBFGS | SSBFGS):
                inner.step = self._guarded_step(inner, trainer)  # type: ignore[method-assign]
                self._wrapped.append(inner)

    def _agreed(self, trainer: L.Trainer) -> bool:
        """Whether any process was asked to stop (a collective under DDP: every process must call it alike); a
        process that was not signalled itself takes on the signal, so it stops and reports as the others do."""
        if trainer.world_size == 1:
            return self.stop.requested
        mine = torch.tensor(self.stop.signum or 0, device=trainer.strategy.root_device)
        signum = int(trainer.strategy.reduce(mine, reduce_op="max"))
        if signum and not self.stop.requested:
            self.stop.signum = signum
        return signum > 0

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, *args: Any) -> None:
        """Stop after this epoch once asked to (its step is taken: its checkpoint follows); under DDP on every
        process once any of them was."""
        if self._agreed(trainer):
            trainer.should_stop = True

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """A signal after the step (during validation, say) stops here, before the next epoch; the checkpoint
        callbacks save this epoch after this hook."""
        if self._agreed(trainer):
            trainer.should_stop = True

    def _guarded_step(self, opt: torch.optim.Optimizer, trainer: L.Trainer) -> Any:
        """L-BFGS's step whose closure reports a zero gradient once a stop is asked for: the line search then
        accepts its next point of sufficient decrease and the gradient test ends the call, so the network stops
        at a point L-BFGS accepted (the true gradient of the next start keeps the history consistent)."""
        step = opt.step

        def guarded(closure: Any = None) -> Any:
            if closure is None:
                return step()

            def closure_checked() -> Any:
                loss = closure()
                if self._agreed(trainer):
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
