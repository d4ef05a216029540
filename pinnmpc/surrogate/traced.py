"""The flow map x(tau) = f([x0, u]) as one torch module of one input, for tracers: nothing in its forward pass reads a
tensor's value into Python (the prior takes adam's torch model, fixes its sub-steps from t_max and keeps no memo), so
torch.fx's make_fx (from which l4casadi builds its C++), torch.jit.trace and torch.func's transforms record the whole
flow. `python -m pinnmpc.export` writes the CasADi, C and ONNX forms; this one is for torch-based tooling such as
l4casadi: `l4casadi.L4CasADi(TracedFlow(load_surrogate(system="panda")))`."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from pinnmpc.surrogate.checkpoint import Surrogate


class TracedFlow(nn.Module):
    """x(tau) for rows (x0, u) side by side, (..., nx + nu) -> (..., nx), in the surrogate's dtype."""

    def __init__(self, surrogate: Surrogate) -> None:
        super().__init__()
        self.model = surrogate.model
        self.nx, self.nu, self.tau = surrogate.nx, surrogate.nu, float(surrogate.tau)

    def forward(self, xu: Tensor) -> Tensor:
        """x(tau) from the rows' first nx entries (x0) under their last nu (u, held)."""
        if xu.shape[-1] != self.nx + self.nu:
            raise ValueError(f"TracedFlow expects rows of nx + nu = {self.nx + self.nu} (x0, u), got {tuple(xu.shape)}")
        x0, u = xu[..., : self.nx], xu[..., self.nx :]
        t = torch.full_like(x0[..., :1], self.tau)
        prior = getattr(self.model, "prior", None)
        if prior is None:
            return self.model(t, x0, u)
        with prior.traceable():
            return self.model(t, x0, u)
