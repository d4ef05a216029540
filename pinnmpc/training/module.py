"""Training logic only: losses, L-BFGS with stall recovery, validation RMSE. The network stays a plain nn.Module."""

from __future__ import annotations

import math
from collections.abc import Sequence

import lightning as L
import torch
from torch import Tensor

from pinnmpc.surrogate.network import PINN
from pinnmpc.surrogate.prior import tensor_key
from pinnmpc.systems.base import System
from pinnmpc.training.settings import OPTIMIZERS, ModuleSettings
from pinnmpc.training.ssbfgs import SSBFGS
from pinnmpc.util.checks import positive, vector

DTYPES = {"float32": torch.float32, "float64": torch.float64}
CAST_MEMO = 32  # training-dtype copies kept (a draw has up to ~10 tensors: collocation, anchors, data, validation)


def lbfgs_evals(opt: torch.optim.Optimizer) -> int:
    """Total function evaluations L-BFGS has made (its state lives on the first parameter)."""
    inner = getattr(opt, "optimizer", opt)
    first = next(iter(inner.param_groups[0]["params"]))
    return int(inner.state.get(first, {}).get("func_evals", 0))


def stalled(start_loss: float, end_loss: float, evals: int, min_evals: int = 3, rel_tol: float = 0.0) -> bool:
    """Whether an L-BFGS call is stuck: too few evaluations (a tolerance was hit), or no progress at all (float32
    line searches that find no decrease spend a whole call of evaluations on it, over and over), or below rel_tol."""
    progress = (start_loss - end_loss) / max(abs(start_loss), 1e-30)
    return evals < min_evals or progress <= 0.0 or progress < rel_tol


class PINNModule(L.LightningModule):
    """Data loss at t = 0 plus ODE-residual loss at collocation points, minimised full-batch.

    Under DDP each process holds a shard of the points (CollocationDataModule); every loss the optimiser or the
    stall test sees is the mean over the processes (so all of them take the same line-search and stall decisions)
    and DDP averages the gradients in manual_backward: the parameters stay identical on every process.

    The keyword defaults are ModuleSettings' (pinnmpc/training/settings.py), the structured config behind
    conf/module/pinn.yaml that `python -m pinnmpc.train` instantiates; experiment=paper is the paper's training.
    """

    def __init__(
        self,
        system: System,
        model: PINN,
        tau: float,
        residual_form: str = ModuleSettings.residual_form,
        residual_scale: Sequence[float] | str = ModuleSettings.residual_scale,
        kinematic_weight: float = ModuleSettings.kinematic_weight,
        weight_physics: float = ModuleSettings.weight_physics,
        weight_data: float = ModuleSettings.weight_data,
        weight_anchor: float = ModuleSettings.weight_anchor,
        weight_robot: float = ModuleSettings.weight_robot,
        robot_delta: float | None = ModuleSettings.robot_delta,
        anchor_state_weight: Sequence[float] | None = ModuleSettings.anchor_state_weight,
        dtype: str = ModuleSettings.dtype,
        adam_epochs: int = ModuleSettings.adam_epochs,
        adam_lr: float = ModuleSettings.adam_lr,
        lbfgs_lr: float = ModuleSettings.lbfgs_lr,
        lbfgs_max_iter: int = ModuleSettings.lbfgs_max_iter,
        lbfgs_history: int = ModuleSettings.lbfgs_history,
        lbfgs_tolerance_grad: float = ModuleSettings.lbfgs_tolerance_grad,
        lbfgs_tolerance_change: float = ModuleSettings.lbfgs_tolerance_change,
        stall_min_evals: int = ModuleSettings.stall_min_evals,
        stall_rel_tol: float = ModuleSettings.stall_rel_tol,
        stall_redraw: bool = ModuleSettings.stall_redraw,
        robust_delta: float | None = ModuleSettings.robust_delta,
        optimizer: str = ModuleSettings.optimizer,
        ssbfgs_variant: str = ModuleSettings.ssbfgs_variant,
        hessian_dtype: str = ModuleSettings.hessian_dtype,
        hessian_buffer: int = ModuleSettings.hessian_buffer,
    ) -> None:
        super().__init__()
        self.save_hyperparameters(ignore=["system", "model"])
        if dtype not in DTYPES:
            raise ValueError(f"unknown dtype {dtype!r}; expected one of {sorted(DTYPES)}")
        if optimizer not in OPTIMIZERS:
            raise ValueError(f"module.optimizer={optimizer!r}; expected one of {list(OPTIMIZERS)}")
        if robust_delta is not None and (
            isinstance(robust_delta, bool)
            or not isinstance(robust_delta, int | float)
            or not 0 < robust_delta < math.inf
        ):
            raise ValueError(f"robust_delta must be a positive number or null, got {robust_delta!r}")
        self.automatic_optimization = False
        self.system = system
        self.model = model.to(DTYPES[dtype])
        self.tau = float(tau)
        scale = self._residual_scale(residual_scale) / self._kinematic_weights(kinematic_weight)
        self.register_buffer("res_scale", scale.to(DTYPES[dtype]))
        weights = self._anchor_weights(anchor_state_weight).to(DTYPES[dtype])
        self.register_buffer("anchor_w", weights, persistent=False)  # a setting, not a weight: resumes take the new
        self.stalls = 0
        self._casts: dict[tuple, tuple[Tensor, Tensor]] = {}  # source identity -> (source, its training-dtype copy)

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        """A resumed run weighs its loss as configured now (module.residual_scale, kinematic_weight), not as the
        checkpoint's run did: the weights are settings, like robust_delta, that a user may change on resume."""
        checkpoint["state_dict"]["res_scale"] = self.res_scale.detach().clone()

    def _residual_scale(self, residual_scale: Sequence[float] | str) -> Tensor:
        """Divide each residual component by its typical size so no state dominates the loss."""
        nx = self.model.nx
        if residual_scale == "auto":
            if self.hparams.residual_form == "explicit":
                return self.model.residual_unit.detach().double()
            return torch.ones(nx, dtype=torch.float64)
        scale = torch.tensor(list(residual_scale), dtype=torch.float64)
        if scale.shape != (nx,) or torch.any(scale <= 0):
            raise ValueError(f"residual_scale must be 'auto' or {nx} positive numbers, got {list(residual_scale)}")
        return scale

    def _anchor_weights(self, weights: Sequence[float] | None) -> Tensor:
        """Per-state multiplier of the anchor loss, so a state whose target is tightest in output units gets more."""
        nx = self.model.nx
        if weights is None:
            return torch.ones(nx, dtype=torch.float64)
        w = list(weights)
        bad = vector(nx, positive())(w, {})
        if bad is not None:
            raise ValueError(f"module.anchor_state_weight={w}; expected null or {bad}")
        return torch.tensor(w, dtype=torch.float64)

    def _kinematic_weights(self, weight: float) -> Tensor:
        """Per-component weight: `weight` on the kinematic rows dq/dt - v of an x = (q, v) state, 1 elsewhere.

        A kinematic residual r over the period moves q(tau) by ~tau r, a dynamics residual moves v by only
        ~T r (the damping forgets it within its time constant T), so with both scaled alike the positions
        drift from the integral of the network's own velocities: weight > 1 holds them to it.
        """
        nx = self.model.nx
        if isinstance(weight, bool) or not isinstance(weight, int | float) or not (0 < weight < math.inf):
            raise ValueError(f"kinematic_weight must be a positive number, got {weight!r}")
        if weight != 1.0 and nx % 2:
            raise ValueError(f"kinematic_weight needs a state (positions, velocities) of even dimension, got {nx}")
        w = torch.ones(nx, dtype=torch.float64)
        w[: nx // 2] = float(weight)
        return w

    def _cast(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        """Training dtype (float32 is the faster on CPU; the surrogate runs in float64 later), on the module's
        device."""
        return {k: self._cast_one(v) for k, v in batch.items()}

    def _cast_one(self, v: Tensor) -> Tensor:
        """The same copy while the same points come (full-batch: every step until a redraw), so what is memoised on
        its inputs, the prior's x_p(t), is computed once per draw rather than once per step."""
        key = tensor_key(v)
        hit = self._casts.get(key)
        if hit is None:
            if len(self._casts) >= CAST_MEMO:
                self._casts.pop(next(iter(self._casts)))
            hit = self._casts[key] = (v, v.to(device=self.res_scale.device, dtype=self.res_scale.dtype))
        return hit[1]

    def _scaled_residual(self, b: dict[str, Tensor]) -> Tensor:
        """ODE residual per point and state, in the units the physics loss weighs."""
        x, dxdt = self.model.with_time_derivative(b["t"], b["x0"], b["u"])
        return self.system.residual(x, dxdt, b["u"], self.hparams.residual_form) / self.res_scale

    @torch.no_grad()
    def pointwise_residual(self, t: Tensor, x0: Tensor, u: Tensor) -> Tensor:
        """Squared residual per point (on the module's device): where residual-adaptive sampling puts the next
        collocation points."""
        b = self._cast({"t": t, "x0": x0, "u": u})
        return self._scaled_residual(b).square().sum(dim=-1).double()

    @staticmethod
    def _penalty(r: Tensor, delta: float | None) -> Tensor:
        """Squares (delta None), or Huber's penalty, linear beyond delta, so that a few large misses (the stiff start
        of each step, joint B's friction switch, a robot's ramped command) do not set the fit everywhere else."""
        if delta is None:
            return r.square()
        a = r.abs()
        return torch.where(a <= delta, a.square(), delta * (2 * a - delta))

    def losses(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        """Physics, data and total loss for one full batch."""
        b = self._cast(batch)
        if self.hparams.weight_physics > 0:
            out = {"physics": self._penalty(self._scaled_residual(b), self.hparams.robust_delta).mean()}
        else:  # no physics loss (fine-tuning on logs alone): its residual, the dearest term, is not evaluated
            out = {"physics": torch.zeros((), dtype=self.res_scale.dtype, device=self.res_scale.device)}
        if "share" in b:  # a DDP shard: weighted so that the mean over the processes is the mean over all points
            out["physics"] = out["physics"] * b["share"]
        total = self.hparams.weight_physics * out["physics"]
        if "data_x0" in b and self.hparams.weight_data > 0:
            x0 = b["data_x0"]
            x_at_0 = self.model(torch.zeros_like(x0[..., :1]), x0, b["data_u"])
            out["data"] = ((x_at_0 - x0) / self.model.out_scale).square().mean()
            total = total + self.hparams.weight_data * out["data"]
        if "anchor_t" in b and self.hparams.weight_anchor > 0:
            dx = self.model(b["anchor_t"], b["anchor_x0"], b["anchor_u"]) - b["anchor_x0"]
            out["anchor"] = (((dx - b["anchor_dx"]) / self.model.out_scale).square() * self.anchor_w).mean()
            if "anchor_share" in b:  # a DDP shard, weighted as the physics loss is
                out["anchor"] = out["anchor"] * b["anchor_share"]
            total = total + self.hparams.weight_anchor * out["anchor"]
        if "robot_t" in b and self.hparams.weight_robot > 0:  # the robot's logs: what the model misses
            dx = self.model(b["robot_t"], b["robot_x0"], b["robot_u"]) - b["robot_x0"]
            miss = (dx - b["robot_dx"]) / self.model.out_scale
            out["robot"] = (self._penalty(miss, self.hparams.robot_delta) * self.anchor_w).mean()
            total = total + self.hparams.weight_robot * out["robot"]
        out["total"] = total
        return out

    def configure_optimizers(self) -> list[torch.optim.Optimizer]:
        """L-BFGS (the paper) or dense self-scaled BFGS, both with strong Wolfe line search, plus an optional Adam
        warm-up."""
        h = self.hparams
        params = [p for p in self.model.parameters() if p.requires_grad]  # a staged model's base stays frozen
        common = dict(
            lr=h.lbfgs_lr,
            max_iter=h.lbfgs_max_iter,
            tolerance_grad=h.lbfgs_tolerance_grad,
            tolerance_change=h.lbfgs_tolerance_change,
        )
        if h.optimizer == "ssbfgs":
            qn: torch.optim.Optimizer = SSBFGS(
                params,
                **common,
                variant=h.ssbfgs_variant,
                hessian_dtype=h.hessian_dtype,
                buffer=h.hessian_buffer,
            )
        else:
            qn = torch.optim.LBFGS(params, **common, history_size=h.lbfgs_history, line_search_fn="strong_wolfe")
        return [qn, torch.optim.Adam(params, lr=h.adam_lr)]

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        """One optimiser call over the full batch; recover from an L-BFGS stall."""
        lbfgs, adam = self.optimizers()
        use_adam = self.current_epoch < self.hparams.adam_epochs
        opt = adam if use_adam else lbfgs

        def closure() -> Tensor:
            opt.zero_grad()
            loss = self.losses(batch)["total"]
            self.manual_backward(loss)  # under DDP: gradients averaged over the processes
            return self._across_processes(loss)

        evals_before = lbfgs_evals(lbfgs)
        start_loss = float(opt.step(closure=closure).detach())  # torch optimizers return the first closure value
        with torch.no_grad():
            parts = self.losses(batch)
        if self.trainer.world_size > 1:  # one collective for all terms: the same numbers on every process
            parts = dict(zip(parts, self._across_processes(torch.stack(list(parts.values())))))
        if not math.isfinite(float(parts["total"])):
            raise FloatingPointError(
                f"training loss became {float(parts['total'])} at epoch {self.current_epoch}; "
                "the last good checkpoint is kept (try a smaller lbfgs_lr or an Adam warm-up)"
            )
        if not use_adam and self._stalled(start_loss, float(parts["total"]), lbfgs_evals(lbfgs) - evals_before):
            self._recover_from_stall(lbfgs)
        for name, value in parts.items():
            self.log(
                f"train/loss_{name}", value, prog_bar=name == "total", on_step=False, on_epoch=True, batch_size=1,
                sync_dist=True,
            )  # fmt: skip
        self.log("train/stalls", float(self.stalls), on_step=False, on_epoch=True, batch_size=1, sync_dist=True)
        return parts["total"]

    def _across_processes(self, value: Tensor) -> Tensor:
        """The mean over the DDP processes of a (detached) loss; the value itself with one process."""
        if self.trainer.world_size == 1:
            return value
        return self.trainer.strategy.reduce(value.detach().clone(), reduce_op="mean")  # in place: a copy

    def _stalled(self, start_loss: float, end_loss: float, evals: int) -> bool:
        """stalled() with this module's stall settings."""
        return stalled(start_loss, end_loss, evals, self.hparams.stall_min_evals, self.hparams.stall_rel_tol)

    def _recover_from_stall(self, opt: torch.optim.Optimizer) -> None:
        """PyTorch's L-BFGS returns at once after hitting a tolerance: forget its history (and redraw points)."""
        inner = getattr(opt, "optimizer", opt)
        inner.state.clear()
        self.stalls += 1
        datamodule = getattr(self.trainer, "datamodule", None)
        if self.hparams.stall_redraw and datamodule is not None and hasattr(datamodule, "draw"):
            datamodule.draw()

    def validation_step(self, batch: dict[str, Tensor], batch_idx: int) -> None:
        """One-step RMSE at t = tau per state against the accurate reference rollouts (a batch with t_split: the
        period split at a command delay, its first t_split s under u_prev, as the controller predicts it)."""
        b = self._cast(batch)
        t, x0 = torch.full_like(b["x0"][..., :1], self.tau), b["x0"]
        if "t_split" in b:
            t, x0 = t - b["t_split"], self.model(b["t_split"], x0, b["u_prev"])
        err = self.model(t, x0, b["u"]) - b["x1"]
        rmse = err.double().square().mean(dim=0).sqrt()
        for name, value in zip(self.system.state_names, rmse):  # sync_dist: the same set on every DDP process
            self.log(f"val/rmse_{name}", value, batch_size=1, sync_dist=True)
        n_pos = len(self.system.state_names) // 2
        self.log("val/rmse_position", rmse[:n_pos].max(), prog_bar=True, batch_size=1, sync_dist=True)
        self.log("val/rmse_velocity", rmse[n_pos:].max(), batch_size=1, sync_dist=True)
