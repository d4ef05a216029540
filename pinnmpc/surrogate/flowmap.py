"""One interface for every model of one sampling period x_k+1 = F(x_k, u_k): the trained surrogate, its numpy
fast path and the true dynamics integrated by RK4 (torch autodiff or compiled C), so the controller's OCP, the
bench and the tests take any of them alike."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, ClassVar, Protocol, runtime_checkable

import casadi as ca
import numpy as np
import torch
from torch import Tensor

from pinnmpc.plant.integrators import n_steps, rk4_step
from pinnmpc.surrogate.checkpoint import Dimensions
from pinnmpc.systems.base import Box, System
from pinnmpc.systems.compiled import BatchedFunction, compile_functions

Array = Any  # a torch Tensor or a numpy array, as the flow map's array_api says
ARRAY_APIS = ("torch", "numpy")


@runtime_checkable
class FlowMap(Protocol):
    """x(tau) from x0 under the zero-hold input u, batched over leading dimensions, with its Jacobians.

    array_api says what step takes: "torch" (tensors, differentiable by autograd: every solver works) or
    "numpy" (arrays: the Gauss-Newton solvers). numpy_flow() is the numpy fast path of the same map, which
    the Gauss-Newton solvers use at batch 1 (itself for numpy maps; None when there is none)."""

    tau: float  # sampling period the map advances by, s
    state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    state_box: Box  # where the map is meant to be evaluated (a surrogate's training box)
    input_box: Box  # the inputs it accepts (the controller's default bounds)
    array_api: ClassVar[str]

    @property
    def nx(self) -> int:
        """State dimension."""
        ...

    @property
    def nu(self) -> int:
        """Input dimension."""
        ...

    def step(self, x0: Array, u: Array) -> Array:
        """x(tau) (..., nx) for x0 (..., nx) and u (..., nu)."""
        ...

    def step_with_jacobian(self, x0: Array, u: Array) -> tuple[Array, Array, Array]:
        """x(tau), A = dx/dx0 (..., nx, nx) and B = dx/du (..., nx, nu)."""
        ...

    def numpy_flow(self) -> FlowMap | None:
        """The same map on numpy arrays (array_api "numpy"), or None when there is no such fast path."""
        ...


def numpy_path(model: Any) -> FlowMap | None:
    """The numpy fast path of a model (None: it has none), so callers never reach into a model's internals."""
    numpy_flow = getattr(model, "numpy_flow", None)
    return numpy_flow() if callable(numpy_flow) else None


def passes_plain_rows(flow: Any) -> bool:
    """Whether the map evaluates plain rows (values alone) in its pass over the nodes (step_with_jacobian_plus):
    asked of its class, since a wrapper's forwarded attribute would be its inner map's."""
    return getattr(type(flow), "step_with_jacobian_plus", None) is not None


def check_flow_map(model: Any) -> None:
    """Fail early, naming what is missing, when an object cannot serve as a FlowMap."""
    missing = [a for a in ("tau", "state_names", "input_names", "state_box", "input_box") if not hasattr(model, a)]
    missing += [m for m in ("step", "step_with_jacobian") if not callable(getattr(model, m, None))]
    if missing:
        raise TypeError(
            f"{type(model).__name__} is not a flow map: it lacks {missing} (see pinnmpc.surrogate.flowmap.FlowMap)"
        )
    api = getattr(model, "array_api", "torch")
    if api not in ARRAY_APIS:
        raise TypeError(f"{type(model).__name__}.array_api={api!r}; expected one of {ARRAY_APIS}")


class _TrueModel(Dimensions):
    """Names and boxes of a system, shared by the true-model flow maps."""

    prediction: ClassVar[str] = "true_model"  # what an NMPC on it predicts with, for metrics.json

    def __init__(self, system: System, tau: float, h: float) -> None:
        if not (tau > 0 and h > 0):
            raise ValueError(f"tau and h must be positive, got tau={tau}, h={h}")
        self.system = system
        self.tau, self.h = float(tau), float(h)
        self.state_names, self.input_names = tuple(system.state_names), tuple(system.input_names)
        self.state_box: Box = system.state_box
        self.input_box: Box = system.input_box
        nx = len(self.state_names)
        self.domain = Box([-math.inf] * nx, [math.inf] * nx)  # the physics holds for every state


class RK4Model(_TrueModel):
    """The true dynamics integrated by RK4 in torch with exact Jacobians (autodiff through RK4): the controller's
    perfect-model baseline, differentiable like the surrogate."""

    array_api: ClassVar[str] = "torch"

    def __init__(self, system: System, tau: float, h: float, jacobian: str = "reverse") -> None:
        if jacobian not in ("reverse", "jacfwd"):
            raise ValueError(f"unknown jacobian mode {jacobian!r}; expected 'reverse' or 'jacfwd'")
        super().__init__(system, tau, h)
        self.jacobian = jacobian
        self.dtype = torch.float64
        self._jacfwd = torch.func.vmap(torch.func.jacfwd(self._flow_with_aux, argnums=(0, 1), has_aux=True))

    def numpy_flow(self) -> None:
        """None: the baseline stays in torch (its rows are measured that way); CompiledRK4 is the numpy one."""
        return None

    def _flow(self, x0: Tensor, u: Tensor) -> Tensor:
        """x(tau) by RK4 with step h over the torch rhs."""
        return rk4_step(self.system.rhs, x0, u, self.tau, self.h)

    def _flow_with_aux(self, x0: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """The flow twice: jacfwd differentiates the first and hands back the second as the value."""
        x1 = self._flow(x0, u)
        return x1, x1

    def step(self, x0: Tensor, u: Tensor) -> Tensor:
        """x(tau): one zero-hold sampling period."""
        return self._flow(x0.to(self.dtype), u.to(self.dtype))

    def step_with_jacobian(self, x0: Tensor, u: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """x(tau), A = dx/dx0 (..., nx, nx) and B = dx/du (..., nx, nu), exact (autodiff through RK4)."""
        lead, nx, nu = x0.shape[:-1], self.nx, self.nu
        xf, uf = x0.to(self.dtype).reshape(-1, nx), u.to(self.dtype).reshape(-1, nu)
        if self.jacobian == "jacfwd":
            (A, B), x1 = self._jacfwd(xf, uf)
        else:
            x1, A, B = self._reverse_jacobian(xf, uf)
        return x1.reshape(*lead, nx), A.reshape(*lead, nx, nx), B.reshape(*lead, nx, nu)

    def _reverse_jacobian(self, x0: Tensor, u: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """One reverse pass over nx copies of the batch, row i seeded with e_i: cheaper here than functorch's jacfwd."""
        nx, nu = self.nx, self.nu
        with torch.enable_grad():
            xr = x0.detach().unsqueeze(-2).expand(-1, nx, nx).clone().requires_grad_(True)
            ur = u.detach().unsqueeze(-2).expand(-1, nx, nu).clone().requires_grad_(True)
            y = self._flow(xr, ur)
            seed = torch.eye(nx, dtype=y.dtype).expand_as(y)
            A, B = torch.autograd.grad(y, (xr, ur), seed)
        return y.detach()[:, 0], A, B


class CompiledRows:
    """step and step_with_jacobian over compiled functions of rows: _step(x, u) -> [x1], _full(x, u) -> [x1, J]
    with J = [A, B] row-major, flat; numpy in and out, any leading shape."""

    nx: int
    nu: int
    _step: Callable[[np.ndarray, np.ndarray], list[np.ndarray]]
    _full: Callable[[np.ndarray, np.ndarray], list[np.ndarray]]

    def _rows(self, x0: np.ndarray, u: np.ndarray) -> tuple[tuple[int, ...], np.ndarray, np.ndarray]:
        """Leading shape and the batch as float64 rows (B, nx), (B, nu)."""
        x0, u = np.asarray(x0, dtype=np.float64), np.asarray(u, dtype=np.float64)
        if x0.shape[-1] != self.nx or u.shape[-1] != self.nu:
            raise ValueError(f"expected x0 (..., {self.nx}) and u (..., {self.nu}), got {x0.shape} and {u.shape}")
        return x0.shape[:-1], x0.reshape(-1, self.nx), u.reshape(-1, self.nu)

    def step(self, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
        """x(tau) (..., nx)."""
        lead, xf, uf = self._rows(x0, u)
        (x1,) = self._step(xf, uf)
        return x1.reshape(*lead, self.nx)

    def step_with_jacobian(self, x0: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x(tau), A (..., nx, nx) and B (..., nx, nu)."""
        lead, xf, uf = self._rows(x0, u)
        x1, jac = self._full(xf, uf)
        jac = jac.reshape(*lead, self.nx, self.nx + self.nu)
        return x1.reshape(*lead, self.nx), jac[..., : self.nx], jac[..., self.nx :]


class CompiledRK4(CompiledRows, _TrueModel):
    """The true dynamics integrated by RK4 over the system's CasADi rhs, generated as C and compiled once: the
    classical integrator at its fastest, numpy in and out, with exact Jacobians by CasADi's AD."""

    array_api: ClassVar[str] = "numpy"

    def __init__(self, system: System, tau: float, h: float) -> None:
        super().__init__(system, tau, h)
        self.steps = n_steps(self.tau, self.h)
        rhs = system.casadi_rhs()
        x, u = ca.MX.sym("x", self.nx), ca.MX.sym("u", self.nu)
        dt = self.tau / self.steps
        tag = f"{system.name}_rk4_{self.steps}"
        one = ca.Function(f"{tag}_one", [x, u], [rk4_step(rhs, x, u, dt, dt)])
        x1 = x
        for _ in range(self.steps):  # one RK4 step as a called function: small C whatever the number of steps
            x1 = one(x1, u)
        jac = ca.jacobian(x1, ca.vertcat(x, u))
        step = ca.Function(f"{tag}_step", [x, u], [x1])
        full = ca.Function(f"{tag}_jac", [x, u], [x1, ca.densify(ca.vec(jac.T))])  # row-major J = [A, B], flat
        lib = compile_functions(tag, [step, full])
        self._step, self._full = BatchedFunction(lib[step.name()]), BatchedFunction(lib[full.name()])

    def numpy_flow(self) -> CompiledRK4:
        """Itself: it already works on numpy arrays."""
        return self


class ExactValues(Dimensions):
    """The true model's predictions with the surrogate's Jacobians: Gauss-Newton on this map converges to plans
    that obey the true dynamics (an inexact-Jacobian Newton method), while the costly sensitivities, which
    dominate a classical solve, still come from one batched network call. The true model is integrated, values only."""

    array_api: ClassVar[str] = "numpy"
    prediction: ClassVar[str] = "exact_values"  # controller.model that builds it, for metrics.json
    approximate_jacobians: ClassVar[bool] = True  # A, B are not the derivatives of step(): solvers' models are inexact

    def __init__(self, surrogate: Any, exact: FlowMap) -> None:
        check_flow_map(surrogate)
        jac = numpy_path(surrogate)
        if jac is None:
            raise TypeError(f"{type(surrogate).__name__} has no numpy fast path (exact values take its Jacobians)")
        if abs(exact.tau - surrogate.tau) > 1e-12:
            raise ValueError(f"the exact model's tau={exact.tau} differs from the surrogate's tau={surrogate.tau}")
        if tuple(exact.state_names) != tuple(surrogate.state_names):
            raise ValueError(
                f"the exact model's states {list(exact.state_names)} differ from the surrogate's "
                f"{list(surrogate.state_names)} (a surrogate of another system?)"
            )
        self.jacobians, self.exact = jac, numpy_path(exact) or exact
        _take_facts(self, surrogate)

    def numpy_flow(self) -> ExactValues:
        """Itself: it already works on numpy arrays."""
        return self

    def step(self, x0: np.ndarray, u: np.ndarray) -> np.ndarray:
        """x(tau) by the true model."""
        return self.exact.step(x0, u)

    def step_with_jacobian(self, x0: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x(tau) by the true model; A and B by the surrogate."""
        _, A, B = self.jacobians.step_with_jacobian(x0, u)
        return self.exact.step(x0, u), A, B


class PriorOnly(CompiledRows, Dimensions):
    """A network's physics prior without the network (controller.model=prior): the exact solve of the arm held as
    its model.prior says (pinnmpc.surrogate.prior), compiled with its Jacobian, for comparing what the network adds
    with what the physics it was trained on already gets. On a long arm with midpoint_arm its Jacobian stands in."""

    array_api: ClassVar[str] = "numpy"
    prediction: ClassVar[str] = "prior"  # controller.model that builds it, for metrics.json

    def __init__(self, surrogate: Any) -> None:
        prior = getattr(getattr(surrogate, "model", None), "prior", None)
        if prior is None:
            raise ValueError(
                "controller.model=prior needs a network with a physics prior (model.prior); this one has none: "
                "use controller.model=surrogate"
            )
        compiled = prior.compiled(surrogate.tau)
        self._step, self._full = compiled.value, compiled.with_jacobian
        self.approximate_jacobians = compiled.stand_in_jacobian  # A, B another prior's: solvers' models inexact
        _take_facts(self, surrogate)

    def numpy_flow(self) -> PriorOnly:
        """Itself: it already works on numpy arrays."""
        return self


def _take_facts(flow: Any, surrogate: Any) -> None:
    """A flow map built on a network takes its period, names, boxes, domain and provenance (meta, for reports)."""
    flow.tau = float(surrogate.tau)
    flow.state_names, flow.input_names = tuple(surrogate.state_names), tuple(surrogate.input_names)
    flow.state_box, flow.input_box = surrogate.state_box, surrogate.input_box
    flow.domain = getattr(surrogate, "domain", None)
    flow.meta = getattr(surrogate, "meta", None)
