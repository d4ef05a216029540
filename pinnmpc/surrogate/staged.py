"""Multi-stage networks: a trained PINN, frozen, plus a correction PINN, merged into one PINN for export."""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from pinnmpc.surrogate.network import PINN

STAGE_BOX = ("state_low", "state_high", "input_low", "input_high", "t_max")  # where the network is trained
STAGE_FORM = ("activation", "ic", "time_basis", "second_order", "periodic", "angle_sums", "prior")  # in/out form
STAGE_SHARED = STAGE_BOX + STAGE_FORM  # what base and correction must share to merge into one network
STAGE_DEFAULTS = {"angle_sums": [], "prior": None}  # settings that checkpoints written before they existed do not hold


def _setting(config: dict, key: str) -> object:
    """A network setting of a checkpoint's config, with its default where the checkpoint predates it."""
    return config.get(key, STAGE_DEFAULTS.get(key))


class StagedPINN(nn.Module):
    """A trained PINN, frozen, plus a correction PINN of the same depth trained on what it still gets wrong.

    Multi-stage training (Wang and Lai 2024): once one network has flattened, a fresh one whose output is
    scaled to the first one's error, fitted with residuals measured in units of the first one's residual level,
    makes fast progress again. Both share the input map and the form of the output (exact initial condition,
    gates, second order), so the sum is itself a PINN: merged() folds them into one wider network with
    block-diagonal layers, and everything downstream sees a plain PINN.
    """

    def __init__(self, base: dict, correction: dict, residual_level: float) -> None:
        super().__init__()
        differ = [k for k in STAGE_SHARED if _setting(base, k) != _setting(correction, k)]
        if differ or len(base["hidden"]) != len(correction["hidden"]):
            raise ValueError(
                f"a correction network must share {list(STAGE_SHARED)} and the depth with its base; differs in "
                f"{differ or ['depth']}: base {[base.get(k) for k in differ or ['hidden']]}, correction "
                f"{[correction.get(k) for k in differ or ['hidden']]}"
            )
        if base["ic"] == "soft":
            raise ValueError("staged training needs an exact initial condition (ic='hard' or 'gated'), got ic='soft'")
        if _setting(base, "prior") is not None:
            kind = (base["prior"] or {}).get("kind") if isinstance(base["prior"], dict) else base["prior"]
            raise ValueError(f"staged training does not support model.prior; got {kind}: set system.network.prior=null")
        if not (math.isfinite(residual_level) and residual_level > 0):
            raise ValueError(f"residual_level must be a positive number, got {residual_level}")
        self.base = PINN(**base).requires_grad_(False)
        self.correction = PINN(**correction)
        self.config = {"base": dict(base), "correction": dict(correction), "residual_level": float(residual_level)}
        self.nx, self.nu, self.t_max = self.base.nx, self.base.nu, self.base.t_max
        self.second_order = self.base.second_order

    @property
    def out_scale(self) -> Tensor:
        """The base network's output scale (the data loss at t = 0 is measured in it)."""
        return self.base.out_scale

    @property
    def residual_unit(self) -> Tensor:
        """Residuals are measured against the base's remaining residual level, so the loss starts near 1."""
        return self.base.residual_unit * self.config["residual_level"]

    def _prior(self, t: Tensor, x0: Tensor) -> tuple[Tensor, Tensor]:
        """The correction's part that does not come from its network (x0, or q0 + v0 t and v0), and d/dt of it."""
        if not self.second_order:
            return x0, torch.zeros_like(x0)
        q0, v0 = x0[..., : self.nx // 2], x0[..., self.nx // 2 :]
        return torch.cat((q0 + v0 * t, v0), dim=-1), torch.cat((v0, torch.zeros_like(v0)), dim=-1)

    def forward(self, t: Tensor, x0: Tensor, u: Tensor) -> Tensor:
        """x(t) of base plus correction."""
        return self.base(t, x0, u) + self.correction(t, x0, u) - self._prior(t, x0)[0]

    def with_time_derivative(self, t: Tensor, x0: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """x(t) and dx/dt of base plus correction (the frozen base without a graph)."""
        with torch.no_grad():
            xb, db = self.base.with_time_derivative(t, x0, u)
        xc, dc = self.correction.with_time_derivative(t, x0, u)
        prior, dprior = self._prior(t, x0)
        return xb + xc - prior, db + dc - dprior

    def merged(self) -> PINN:
        """One PINN computing exactly base + correction: layers stacked block-diagonally, the correction's output
        rows rescaled from its output scale to the base's."""
        base, corr = self.base, self.correction
        config = {**base.config, "hidden": [a + b for a, b in zip(base.config["hidden"], corr.config["hidden"])]}
        out = PINN(**config).to(base.out_scale.dtype)
        ratio = (corr.head_scale / base.head_scale).repeat(base.n_gates)  # per network output (gate-major)
        layers = list(zip(out.net.layers, base.net.layers, corr.net.layers))
        with torch.no_grad():
            for i, (m, a, b) in enumerate(layers):
                if i == len(layers) - 1:
                    m.weight.copy_(torch.cat((a.weight, ratio[:, None] * b.weight), dim=1))
                    m.bias.copy_(a.bias + ratio * b.bias)
                elif i == 0:
                    m.weight.copy_(torch.cat((a.weight, b.weight), dim=0))
                    m.bias.copy_(torch.cat((a.bias, b.bias)))
                else:
                    m.weight.copy_(torch.block_diag(a.weight, b.weight))
                    m.bias.copy_(torch.cat((a.bias, b.bias)))
        return out


def pinn_from_state(config: dict, state: dict[str, Tensor]) -> PINN:
    """The network a checkpoint holds: a PINN, or a staged one merged into a single PINN."""
    staged = "base" in config and "correction" in config
    model = StagedPINN(**config) if staged else PINN(**config)
    first = next(iter(state.values()), None)
    if first is not None:
        model = model.to(first.dtype)  # keep float64 weights exact
    model.load_state_dict(state)
    return model.merged() if staged else model
