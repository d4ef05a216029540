"""The small protocol every controlled system implements, so PINN, plant and controller stay generic."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch
from torch import Tensor


@dataclass(frozen=True)
class Box:
    """Axis-aligned box: the region a surrogate was trained on, or the input bounds."""

    low: tuple[float, ...]
    high: tuple[float, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "low", tuple(float(v) for v in self.low))
        object.__setattr__(self, "high", tuple(float(v) for v in self.high))
        if len(self.low) != len(self.high):
            raise ValueError(f"box bounds differ in length: low has {len(self.low)}, high has {len(self.high)}")
        bad = [i for i, (lo, hi) in enumerate(zip(self.low, self.high)) if not lo <= hi]
        if bad:
            i = bad[0]
            raise ValueError(f"box bound {i}: low {self.low[i]} > high {self.high[i]}; expected low <= high")

    @property
    def dim(self) -> int:
        """Number of coordinates."""
        return len(self.low)

    def tensors(self, dtype: torch.dtype = torch.float64) -> tuple[Tensor, Tensor]:
        """Bounds as tensors, for clamping and normalisation."""
        return torch.tensor(self.low, dtype=dtype), torch.tensor(self.high, dtype=dtype)

    def excess(self, points: Tensor) -> Tensor:
        """How far each point lies outside the box (0 inside), per coordinate."""
        lo, hi = self.tensors(points.dtype)
        return torch.clamp(lo - points, min=0) + torch.clamp(points - hi, min=0)


@runtime_checkable
class System(Protocol):
    """A controlled arm dx/dt = rhs(x, u) with x = (q, v), positions first; batched over leading dimensions.

    Everything downstream (PINN, training, plant, controllers, references, plots, bench) asks only this."""

    name: str
    tau: float  # control period of the zero-order hold, s
    nq: int  # joints: x has 2 nq entries
    state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    state_units: tuple[str, ...]
    input_units: tuple[str, ...]
    state_box: Box
    input_box: Box
    joint_limits: Box | None  # joint position limits (nq entries; None: none, e.g. joints that turn all the way round)

    def rhs(self, x: Any, u: Any) -> Any:
        """dx/dt for x (..., nx), u (..., nu): torch tensors (differentiable) or numpy arrays (the plant)."""
        ...

    def fast_rhs(self, x: Tensor, u: Tensor) -> Tensor:
        """dx/dt on large batches (training, reference flows): first-order differentiable, cheapest path."""
        ...

    def residual(self, x: Tensor, dxdt: Tensor, u: Tensor, form: str) -> Tensor:
        """ODE residual in the chosen form ('explicit': dxdt - rhs; 'mass': M-multiplied where available)."""
        ...

    def casadi_rhs(self) -> Any:
        """dx/dt as a CasADi Function (x, u) -> dx: the same physics for the classical NMPC."""
        ...

    def casadi_inverse_dynamics(self, coulomb_width: float | None = None) -> Any:
        """r(q, v, a, u) = M(q) a + h(q, v) - tau(q, v, u) as a CasADi Function: collocation without M^-1 (a sign(v)
        friction smoothed as tanh(v / coulomb_width) where the arm has one)."""
        ...

    def with_mismatch(self, friction_scale: float = 1.0, mass_scale: float = 1.0) -> System:
        """The same arm with scaled friction and inertia: a plant the controller does not know."""
        ...

    def kinematics(self, q: np.ndarray) -> np.ndarray:
        """Points to draw (N, k, 3), base first and tool tip last, for joint positions q (N, nq)."""
        ...


def check_shapes(system: System, x: Tensor, u: Tensor) -> None:
    """Fail early with a readable message instead of a broadcasting error deep in the physics."""
    nx, nu = len(system.state_names), len(system.input_names)
    if x.shape[-1] != nx:
        raise ValueError(f"{system.name}: state has last dimension {x.shape[-1]}, expected {nx} {system.state_names}")
    if u.shape[-1] != nu:
        raise ValueError(f"{system.name}: input has last dimension {u.shape[-1]}, expected {nu} {system.input_names}")
