"""A network on a robot that starts each new command late: x(tau) = G(tau - d, G(d, x0, u_prev), u).

A Franka's joint velocity command does not step when the controller sends it: franky plans a jerk-limited move from
the last command to the new one and libfranka filters it, so over a period's first milliseconds the servo still
tracks about the command before (docs/franka.md). No map of (x0, u) sees that; a network G trained on the arm under
a held input sees it once its flow is split there: the period's first `command_delay` s under the previous input,
the rest under the new one. The map has inputs (u, u_prev) and `previous_input` in its meta, so the controller runs
it on states that carry the input applied last (pinnmpc.surrogate.previous_input); the networks come from
`model.command_delay` (pinnmpc.training.run), which also fits their robot data from that time into each period.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from pinnmpc.surrogate.checkpoint import Dimensions
from pinnmpc.systems.previous_input import doubled_inputs

Array = Any  # a torch Tensor or a numpy array, as the parts' array_api says


class DelayedCommandFlow(Dimensions):
    """x(tau) for x0 (..., nx) and (u, u_prev) (..., 2 nu): `first` (a flow over delay s) under u_prev, then
    `second` (over tau - delay s) under u; both flow maps of one network under a held input."""

    def __init__(self, first: Any, second: Any, delay: float, source: Any) -> None:
        self.first, self.second, self.delay = first, second, float(delay)
        self.array_api: str = getattr(first, "array_api", "torch")
        self.tau = float(first.tau) + float(second.tau)
        self.state_names = tuple(source.state_names)
        self.input_names, self.input_box = doubled_inputs(source.input_names, source.input_box)
        self.state_box, self.domain = source.state_box, source.domain
        self.meta = {**source.meta, "previous_input": True}
        self._source = source
        self._numpy: DelayedCommandFlow | None = None

    @classmethod
    def of(cls, surrogate: Any) -> DelayedCommandFlow:
        """The surrogate's network split at its meta's command_delay (s)."""
        delay = float(surrogate.meta["command_delay"])
        if not 0.0 < delay < surrogate.tau:
            raise ValueError(
                f"command_delay={delay:g} s in the network's meta; expected 0 < delay < its period {surrogate.tau:g} s"
            )
        parts = (surrogate.at(delay), surrogate.at(surrogate.tau - delay))
        return cls(*parts, delay, surrogate)

    @property
    def approximate_jacobians(self) -> bool:
        """The parts' (their prior's stand-in Jacobian)."""
        return bool(getattr(self.first, "approximate_jacobians", False))

    def _split(self, u: Array) -> tuple[Array, Array]:
        """u and u_prev of inputs (..., 2 nu)."""
        nu = len(self.input_names) // 2
        return u[..., :nu], u[..., nu:]

    def step(self, x0: Array, u: Array) -> Array:
        """x(tau): the delay under u_prev, the rest under u."""
        now, before = self._split(u)
        return self.second.step(self.first.step(x0, before), now)

    def step_with_jacobian(self, x0: Array, u: Array) -> tuple[Array, Array, Array]:
        """x(tau), A = dx/dx0 and B = dx/d(u, u_prev) by the chain rule through the split."""
        now, before = self._split(u)
        x1, a1, b1 = self.first.step_with_jacobian(x0, before)
        x2, a2, b2 = self.second.step_with_jacobian(x1, now)
        join = torch.cat if isinstance(x2, torch.Tensor) else np.concatenate
        return x2, a2 @ a1, join((b2, a2 @ b1), -1)

    def numpy_flow(self) -> DelayedCommandFlow | None:
        """The same map over the network's numpy fast path (None where it has none)."""
        if self.array_api == "numpy":
            return self
        if self._numpy is None:
            first, second = (getattr(p, "numpy_flow", None) for p in (self.first, self.second))
            if callable(first) and callable(second):
                self._numpy = DelayedCommandFlow(first(), second(), self.delay, self._source)
        return self._numpy


def controller_flow(surrogate: Any) -> Any:
    """The map a controller predicts with: the network split at its command_delay where its meta has one, else
    itself."""
    meta = getattr(surrogate, "meta", None)
    if isinstance(meta, dict) and meta.get("command_delay") and not isinstance(surrogate, DelayedCommandFlow):
        return DelayedCommandFlow.of(surrogate)
    return surrogate
