"""A network that takes the previous input, (x0, u, u_prev) -> x(tau), as a flow map on states that carry u_prev.

The controller's horizon needs x_{i+1} = F(x_i, u_i, u_{i-1}): with the state s = (x, p), p the input applied over
the period before, that is s_{i+1} = (F(x_i, u_i, p_i), u_i), a plain flow map s -> s' under u, and every solver,
the estimator and the joint limits work on it unchanged (pinnmpc.controller.previous_input feeds p from the input
it applied last). The networks come from `model.previous_input=true` (pinnmpc.systems.previous_input).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from pinnmpc.surrogate.checkpoint import Dimensions
from pinnmpc.surrogate.flowmap import passes_plain_rows
from pinnmpc.systems.base import Box
from pinnmpc.systems.previous_input import WithPreviousInput, takes_previous_input

Array = Any  # a torch Tensor or a numpy array, as the wrapped map's array_api says


class PreviousInputFlow:
    """The flow map s = (x, p) -> (F(x, u, p), u) of a network F whose inputs are (u, u_prev)."""

    def __init__(self, flow: Any) -> None:
        n_in = len(flow.input_names)
        if n_in % 2:
            raise ValueError(
                f"a network that takes the previous input has inputs (u, u_prev); this one has {n_in}: "
                f"{list(flow.input_names)}"
            )
        self.flow, self._x, self._u = flow, len(flow.state_names), n_in // 2
        nu, inputs, states = self._u, flow.input_box, flow.state_box
        self.array_api: str = getattr(flow, "array_api", "torch")  # the wrapped map's arrays
        self.tau = flow.tau
        self.state_names = (*flow.state_names, *flow.input_names[nu:])
        self.input_names = tuple(flow.input_names[:nu])
        self.state_box = Box((*states.low, *inputs.low[nu:]), (*states.high, *inputs.high[nu:]))
        self.input_box = Box(inputs.low[:nu], inputs.high[:nu])
        self.nq = self._x // 2  # the arm's joints: its states (q, v) come first
        self._numpy: PreviousInputFlow | None = None
        self._eye = np.eye(nu)  # d u / d u: the lower block of every B

    def __getattr__(self, name: str) -> Any:
        """Every other fact (meta, domain, the model, approximate_jacobians) is the wrapped map's."""
        if name == "flow":  # not set yet (copying): no recursion through __getattr__
            raise AttributeError(name)
        return getattr(self.flow, name)

    @property
    def nx(self) -> int:
        """The arm's states and the previous input."""
        return self._x + self._u

    @property
    def nu(self) -> int:
        """The arm's inputs."""
        return self._u

    def _network_inputs(self, s: Array, u: Array) -> tuple[Array, Array]:
        """x and (u, p) of states s (..., nx + nu) and inputs u (..., nu)."""
        x, p = s[..., : self._x], s[..., self._x :]
        if isinstance(s, torch.Tensor):
            return x, torch.cat(torch.broadcast_tensors(u, p), dim=-1)
        if u.shape == p.shape:  # the controller's calls: no broadcasting (its Python wrapper costs more than the join)
            return x, np.concatenate((u, p), axis=-1)
        return x, np.concatenate(np.broadcast_arrays(u, p), axis=-1)

    def step(self, s: Array, u: Array) -> Array:
        """(x(tau), u) for s = (x0, u_prev) (..., nx + nu) and u (..., nu)."""
        x, inputs = self._network_inputs(s, u)
        y = self.flow.step(x, inputs)
        if isinstance(y, torch.Tensor):
            return torch.cat((y, inputs[..., : self._u]), dim=-1)
        return np.concatenate((y, inputs[..., : self._u]), axis=-1)

    def step_with_jacobian(self, s: Array, u: Array) -> tuple[Array, Array, Array]:
        """(x(tau), u), A = d/ds (..., nx + nu, nx + nu) and B = d/du (..., nx + nu, nu): the network's Jacobians
        in the upper rows, u passed on below."""
        x, inputs = self._network_inputs(s, u)
        return self._carried(*self.flow.step_with_jacobian(x, inputs), inputs)

    def step_with_jacobian_plus(
        self, s: np.ndarray, u: np.ndarray, s_plain: np.ndarray, u_plain: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """step_with_jacobian at (s, u) and step at rows (s_plain, u_plain): one pass where the wrapped map has
        one (pinnmpc.surrogate.numpy_flow), else two."""
        if not passes_plain_rows(self.flow):
            return (*self.step_with_jacobian(s, u), self.step(s_plain, u_plain))
        x, inputs = self._network_inputs(s, u)
        x_plain, inputs_plain = self._network_inputs(s_plain, u_plain)
        y, a, b, y_plain = self.flow.step_with_jacobian_plus(x, inputs, x_plain, inputs_plain)
        plain = np.concatenate((y_plain, inputs_plain[..., : self._u]), axis=-1)
        return (*self._carried(y, a, b, inputs), plain)

    def _carried(self, y: Array, a: Array, b: Array, inputs: Array) -> tuple[Array, Array, Array]:
        """The network's step and Jacobians at (x, (u, p)) as the map's on s: u passed on below."""
        nx, nu, lead = self._x, self._u, y.shape[:-1]
        torch_side = isinstance(y, torch.Tensor)
        zeros = (lambda *shape: y.new_zeros(shape)) if torch_side else (lambda *shape: np.zeros(shape))
        big_a, big_b = zeros(*lead, nx + nu, nx + nu), zeros(*lead, nx + nu, nu)
        big_a[..., :nx, :nx], big_a[..., :nx, nx:] = a, b[..., nu:]
        big_b[..., :nx, :] = b[..., :nu]
        big_b[..., nx:, :] = torch.eye(nu, dtype=y.dtype) if torch_side else self._eye
        out = torch.cat((y, inputs[..., :nu]), dim=-1) if torch_side else np.concatenate((y, inputs[..., :nu]), -1)
        return out, big_a, big_b

    def numpy_flow(self) -> PreviousInputFlow | None:
        """The same map over the wrapped map's numpy fast path (None where it has none)."""
        if self.array_api == "numpy":
            return self
        if self._numpy is None:
            fast = getattr(self.flow, "numpy_flow", None)
            fast = fast() if callable(fast) else None
            self._numpy = None if fast is None else PreviousInputFlow(fast)
        return self._numpy


class RowValuesFlow(Dimensions):
    """A flow map on inputs (u, u_prev) whose values come from another model, row by row (`values(x0, inputs, tau)`
    on (B, nx) and (B, 2 nu)), and whose Jacobians are a network's (one given the previous input: its own; a plain
    one: none in u_prev): the controller predicting with, say, a robot's own dynamics (examples/*_model_floor.py)."""

    array_api = "numpy"

    def __init__(self, values: Callable[..., np.ndarray], network: Any, system: Any) -> None:
        with_previous = WithPreviousInput(system)
        self.values, self.network, self.tau = values, network.numpy_flow(), system.tau
        self.hears_previous = takes_previous_input(network)
        self.state_names, self.input_names = tuple(system.state_names), tuple(with_previous.input_names)
        self.state_box, self.input_box = system.state_box, with_previous.input_box
        self.domain = Box([-np.inf] * len(self.state_names), [np.inf] * len(self.state_names))
        self.meta = {"previous_input": True}  # the controller feeds u_prev (pinnmpc.controller.previous_input)

    def numpy_flow(self) -> RowValuesFlow:
        """Itself: numpy in and out."""
        return self

    def step(self, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
        """x(tau) row by row (..., nx) for x0 (..., nx) and (u, u_prev) (..., nu)."""
        lead = np.shape(x0)[:-1]
        rows = np.broadcast_arrays(np.reshape(x0, (-1, self.nx)), np.reshape(u, (-1, self.nu)))
        return np.reshape(self.values(*rows, self.tau), (*lead, self.nx))

    def step_with_jacobian(self, x0: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """step's values; A and B of the network."""
        x0, u = np.ascontiguousarray(x0), np.ascontiguousarray(u)
        if self.hears_previous:
            _, a, b = self.network.step_with_jacobian(x0, u)
            return self.step(x0, u), a, b
        _, a, b = self.network.step_with_jacobian(x0, np.ascontiguousarray(u[..., : self.nu // 2]))
        return self.step(x0, u), a, np.concatenate((b, np.zeros_like(b)), axis=-1)
