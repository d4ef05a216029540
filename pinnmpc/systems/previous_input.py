"""A system whose inputs carry the period before's too: what a network learns from when the robot's actuator lags.

A robot whose actuator filters its command (a motor current loop, a velocity ramp) still carries part of the last
period's input into this one, so (x0, u) alone does not fix x(t): the previous input does, nearly (a lag shorter than
the period has settled to it by the period's start). `WithPreviousInput(system)` is the same system with the inputs
(u, u_prev): the model's physics ignore u_prev (the network's physics residual stays the nominal one), the logs
supply it, and the controller feeds it from the input it applied last (pinnmpc.surrogate.previous_input).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from pinnmpc.systems.base import Box

SUFFIX = "_prev"  # the name of u_prev's entries: the input's name and this


def doubled_inputs(names: Sequence[str], box: Box) -> tuple[tuple[str, ...], Box]:
    """The names and box of inputs (u, u_prev) from u's: u_prev's names end in SUFFIX, its box is u's."""
    return (*names, *(f"{n}{SUFFIX}" for n in names)), Box((*box.low, *box.low), (*box.high, *box.high))


class WithPreviousInput:
    """`system` with inputs (u, u_prev): its input box twice, its dynamics of u alone; every other fact its own."""

    def __init__(self, system: Any) -> None:
        if isinstance(system, WithPreviousInput):
            raise ValueError(f"system {system.name} already takes the previous input; expected a plain system")
        self.base = system
        self.arm_nu = len(system.input_names)  # the arm's inputs, the first of these
        self.input_names, self.input_box = doubled_inputs(system.input_names, system.input_box)
        self.input_units = (*system.input_units, *system.input_units)

    def __getattr__(self, name: str) -> Any:
        """Every fact besides the inputs is the system's own."""
        if name == "base":  # not set yet (copying): no recursion through __getattr__
            raise AttributeError(name)
        return getattr(self.base, name)

    def rhs(self, x: Any, u: Any) -> Any:
        """dx/dt of the system under u (the first nu inputs); u_prev does not enter the model."""
        return self.base.rhs(x, u[..., : self.arm_nu])

    def fast_rhs(self, x: Any, u: Any) -> Any:
        """fast_rhs of the system under u alone."""
        return self.base.fast_rhs(x, u[..., : self.arm_nu])

    def residual(self, x: Any, dxdt: Any, u: Any, form: str) -> Any:
        """The system's ODE residual under u alone."""
        return self.base.residual(x, dxdt, u[..., : self.arm_nu], form)


def takes_previous_input(model: Any) -> bool:
    """Whether a network (its surrogate, or its meta) was trained on the previous input too."""
    meta = model if isinstance(model, dict) else getattr(model, "meta", None)
    return isinstance(meta, dict) and bool(meta.get("previous_input"))


def with_previous(u: Tensor) -> Tensor:
    """(u_k, u_{k-1}) for each step of an input sequence (steps, nu), the first step's own input as the one before it
    (a lag that starts settled): what a network given the previous input takes along an open-loop rollout."""
    return torch.cat((u, torch.cat((u[:1], u[:-1]))), dim=-1)


def arm_system(system: Any) -> Any:
    """The arm itself: a WithPreviousInput's system, any other system as it is."""
    return system.base if isinstance(system, WithPreviousInput) else system
