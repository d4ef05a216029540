"""Receding-horizon controller: make_step(x) -> u, with warm start and a safe fallback."""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from pinnmpc.controller.base import Controller, StepStats
from pinnmpc.controller.estimator import OffsetFree, late_notch
from pinnmpc.controller.ocp import HorizonOCP
from pinnmpc.controller.solvers import NO_WARM, Problem, SolveInfo, Solver
from pinnmpc.surrogate.checkpoint import Surrogate

__all__ = ["NMPC", "Controller", "StepStats"]  # the shared interface lives in controller/base.py


@dataclass
class NMPC:
    """NMPC on a surrogate: solves the horizon OCP, applies the first input, shifts the rest as warm start."""

    ocp: HorizonOCP
    solver: Solver
    u_low: Sequence[float]
    u_high: Sequence[float]
    warm_start: bool = True
    disturbance_gain: float = 0.0  # offset-free MPC: 0 off; 1 d = the last one-step prediction error; between: filtered
    disturbance_max: Sequence[float] | None = None  # per-state bound on |d| (None: unbounded)
    disturbance_notch: bool = False  # average the last two prediction errors first (pinnmpc.controller.estimator)
    delay_periods: int = 0  # 1: each input runs a period after its state (plant.command_at = tau): plan ahead
    notch_when_late: bool = False  # the notch on while the plant runs a period late (controller.disturbance.notch=null)
    stats: list[StepStats] = field(default_factory=list)

    def __post_init__(self) -> None:
        nu = self.ocp.nu
        self.low = torch.as_tensor(self.u_low, dtype=torch.float64)
        self.high = torch.as_tensor(self.u_high, dtype=torch.float64)
        if self.low.shape != (nu,) or self.high.shape != (nu,):
            raise ValueError(
                f"input bounds must have {nu} entries each, got {list(self.u_low)} and {list(self.u_high)}"
            )
        if not (torch.isfinite(self.low).all() and torch.isfinite(self.high).all()):
            raise ValueError(
                f"input bounds u_low={self.low.tolist()}, u_high={self.high.tolist()}; expected finite numbers"
            )
        if torch.any(self.low > self.high):
            raise ValueError(f"input lower bound {self.low.tolist()} exceeds upper bound {self.high.tolist()}")
        self._low, self._high = self.low.numpy(), self.high.numpy()
        self._estimator = OffsetFree(self.ocp.nx, self.disturbance_gain, self.disturbance_max, self.disturbance_notch)
        self.reset()

    @property
    def horizon(self) -> int:
        """Prediction horizon H."""
        return self.ocp.horizon

    def describe(self) -> dict[str, Any]:
        """Solver, offset-free gain and what predicts (surrogate, exact_values or prior), for metrics.json and
        headlines."""
        return {
            "controller": "pinn",
            "solver": type(self.solver).__name__,
            "disturbance_gain": self.disturbance_gain,
            "disturbance_notch": self._estimator.notch,
            "prediction": getattr(self.ocp.model, "prediction", "surrogate"),
            "real_time": bool(getattr(self.solver, "rti", False)),  # one step per sample: unconverged by design
            "rti_steps": getattr(self.solver, "rti_steps", None),
            "rti_trust": getattr(self.solver, "rti_trust", None),  # a step beyond it: that sample solved fully
        }

    @property
    def surrogate(self) -> Surrogate:
        """The model the controller predicts with."""
        return self.ocp.surrogate

    @property
    def U(self) -> Tensor:  # noqa: N802
        """The plan the next solve starts from (the last solution shifted by one step), (H, nu)."""
        return torch.from_numpy(self._U)

    @U.setter
    def U(self, plan: Tensor | np.ndarray) -> None:  # noqa: N802
        """Seed the next solve's start, e.g. with a plan from elsewhere."""
        plan = np.array(plan, dtype=np.float64)
        if plan.shape != (self.horizon, self.ocp.nu):
            raise ValueError(f"plan must be ({self.horizon}, {self.ocp.nu}) (horizon, nu), got {plan.shape}")
        self._U = plan
        self._warm = NO_WARM  # the last solve's warm state belongs to its own plan, not to this one

    @property
    def u_prev(self) -> Tensor:
        """The input applied last (the rate penalty's u_{-1})."""
        return torch.from_numpy(self._u_prev)

    @u_prev.setter
    def u_prev(self, u: Tensor | np.ndarray) -> None:
        """Set the input treated as applied last."""
        u = np.array(u, dtype=np.float64)
        if u.shape != (self.ocp.nu,):
            raise ValueError(f"u_prev must have {self.ocp.nu} entries, got shape {u.shape}")
        self._u_prev = u

    def reset(self) -> None:
        """Forget the warm start and the last applied input (start of a new run)."""
        self._U = self._cold_start()
        self._u_prev = self._U[0].copy()
        self._warm: Any = NO_WARM  # the solver's own state from the last solve, handed back to the next one
        self._last: tuple[np.ndarray, np.ndarray] | None = None  # the last measured state and the input applied
        self._predicted: np.ndarray | None = None  # the undisturbed surrogate's x after that input, if the plan had it
        self.ocp.disturbance = None
        self._estimator.notch = late_notch(self.disturbance_notch, self.notch_when_late, self.delay_periods)
        self._estimator.reset()
        self.stats = []

    def _cold_start(self) -> np.ndarray:
        """Zero inputs projected onto the box."""
        return np.clip(np.zeros((self.horizon, self.ocp.nu)), self._low, self._high)

    def clip(self, u: Tensor) -> Tensor:
        """Project onto the input box."""
        return torch.maximum(torch.minimum(u, self.high), self.low)

    def solve(
        self, x0: Tensor, x_ref: Tensor, U0: Tensor, u_prev: Tensor, warm: Any = NO_WARM
    ) -> tuple[Tensor, SolveInfo, Any]:
        """Batched OCP: x0 (B, nx), x_ref (B, H, nx), U0 (B, H, nu), u_prev (B, nu); warm: see Solver.

        Returns the inputs, the statistics and the solver's warm state for the shifted problems."""
        if x_ref.shape[-2] != self.horizon:
            raise ValueError(f"x_ref must cover the horizon: got {x_ref.shape[-2]} steps, expected {self.horizon}")
        problem = Problem(self.ocp, x0, x_ref, u_prev, self.low, self.high)
        U, info, next_warm = self.solver.solve(problem, self.clip(U0), warm)
        return self.clip(torch.as_tensor(U)), info, next_warm

    @property
    def warm(self) -> Any:
        """The solver's warm state the next make_step hands back to it (NO_WARM: a cold start)."""
        return self._warm

    def _checked(self, x: np.ndarray | Tensor, x_ref: np.ndarray | Tensor) -> tuple[np.ndarray, np.ndarray]:
        """The measured state (nx,) and reference (H, nx) as float64 arrays, their shapes checked first."""
        x0, ref = _array(x), _array(x_ref)
        if x0.shape != (self.ocp.nx,):
            raise ValueError(f"the state must have {self.ocp.nx} entries, got shape {x0.shape}")
        if ref.shape != (self.horizon, self.ocp.nx):
            want = (self.horizon, self.ocp.nx)
            raise ValueError(f"x_ref must cover the horizon: expected {want[0]} x {want[1]}, got {ref.shape}")
        limits = self.ocp.joint_limits
        return x0, ref if limits is None else limits.governed(ref)

    def _solve_one(self, x0: np.ndarray, x_ref: np.ndarray) -> tuple[np.ndarray, SolveInfo, Any]:
        """One problem in the solver's own array library: batch-1 solves are dominated by per-call overhead, so a
        solver's warm_step (a warm sample without solve()'s batch handling) goes first where it has one."""
        warm_step = getattr(self.solver, "warm_step", None)
        if warm_step is not None:
            out = warm_step(self.ocp, x0, self._U, x_ref, self._u_prev, self._low, self._high, self._warm)
            if out is not None:
                return np.minimum(np.maximum(out[0], self._low), self._high), out[1], out[2]
        args = (x0[None], self._U[None], x_ref[None], self._u_prev[None], self._low, self._high)
        if self.solver.array_api != "numpy":
            args = tuple(torch.from_numpy(np.ascontiguousarray(a)) for a in args)
        x0b, U0, refb, u_prev, low, high = args
        U, info, next_warm = self.solver.solve(Problem(self.ocp, x0b, refb, u_prev, low, high), U0, self._warm)
        return np.minimum(np.maximum(np.asarray(U, dtype=np.float64)[0], self._low), self._high), info, next_warm

    def make_step(self, x: np.ndarray | Tensor, x_ref: np.ndarray | Tensor) -> np.ndarray:
        """Input to apply now, given the measured state and the next H reference states."""
        x0, ref = self._checked(x, x_ref)
        start = time.perf_counter()
        fallback = False
        ahead = None
        try:
            self._estimate_disturbance(x0)
            ahead = self._ahead(x0) if self.delay_periods else None
            U, info, next_warm = self._solve_one(x0 if ahead is None else ahead[1], ref)
            self.ocp.settle()  # a solver that never evaluated the model at the nodes
            # one problem: its bounded inputs sum finite exactly where each one is, and its one cost
            ok = math.isfinite(float(U.sum())) and math.isfinite(float(info.cost[0]))
        except (RuntimeError, FloatingPointError, np.linalg.LinAlgError):  # e.g. a singular solve on NaN outputs
            ok, info, next_warm = False, None, NO_WARM
            with contextlib.suppress(RuntimeError, FloatingPointError, np.linalg.LinAlgError):
                self.ocp.settle()  # the estimate as before the solve failed
        if not ok:
            fallback = True
            # self._U is already the previous plan shifted: its first entry is the input planned for now
            U = np.clip(np.nan_to_num(self._U, nan=0.0, posinf=0.0, neginf=0.0), self._low, self._high)
        elapsed = time.perf_counter() - start
        self._U = self._shifted(U) if self.warm_start else self._cold_start()
        self._warm = next_warm if self.warm_start and not fallback else NO_WARM
        running = self._u_prev  # the input the plant holds over the coming period when it runs a period late
        self._u_prev = U[0].copy()
        if self.delay_periods:
            self._last, self._predicted = (x0.copy(), running), None if ahead is None else ahead[0]
        else:
            self._last = (x0.copy(), self._u_prev)
            self._predicted = self._planned_next(info) if not fallback else None
        self.stats.append(
            StepStats(
                time_s=elapsed,
                iterations=int(info.iterations[0]) if info is not None else 0,
                cost=float(info.cost[0]) if info is not None else float("nan"),
                converged=bool(info.converged[0]) if info is not None and not fallback else False,
                fallback=fallback,
            )
        )
        return U[0].copy()

    def applied_input(self, u: np.ndarray) -> None:
        """The input the plant sent in place of the last one planned (a robot's safety layer clipped it): the next
        solve's u_{-1}, and the one its prediction and estimate start from."""
        self._u_prev = np.array(u, dtype=np.float64)
        if self._last is not None and not self.delay_periods:
            self._last, self._predicted = (self._last[0], self._u_prev), None

    def _ahead(self, x0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Delay compensation: the model's next state under the input already running, undisturbed and with the
        offset-free estimate added (the state the next input meets)."""
        nxt = -self.ocp.prediction_error(x0, self._u_prev, np.zeros_like(x0))  # F(x0, u) = -(0 - F(x0, u))
        d = self.ocp.disturbance
        return nxt, nxt if d is None else nxt + d

    def prediction_error(self, x_prev: np.ndarray, u_prev: np.ndarray, x: np.ndarray) -> np.ndarray:
        """What the controller's model missed over the last period, x - F(x_prev, u_prev): the closed loop's model
        monitor (no disturbance estimate added)."""
        return self.ocp.prediction_error(x_prev, u_prev, x)

    @property
    def disturbance(self) -> np.ndarray | None:
        """The disturbance the last solve predicted with (None: off or not estimated yet)."""
        return self.ocp.disturbance

    def _estimate_disturbance(self, x: np.ndarray) -> None:
        """Offset-free MPC: what the surrogate missed over the last period, added to every predicted step
        (filtered by the gain, bounded by disturbance_max, notched if asked), so a smooth model error is not
        tracked as offset."""
        if not self._estimator.on or self._last is None:
            return
        predicted = self._predicted
        if predicted is None:  # the model's step rides with the solve's pass over the nodes (HorizonOCP)
            self.ocp.defer_estimate(*self._last, lambda step: self._estimator.update(x - step))
            return
        self.ocp.estimated(self._estimator.update(x - predicted))

    def _planned_next(self, info: SolveInfo) -> np.ndarray | None:
        """The undisturbed prediction of the next state from the plan's own states (saves a network call); None
        where they are not the model's prediction: linearised with Jacobians of another model (exact_values), or
        a solve that stopped short (a real-time iteration's linearised states, an unconverged lifted iterate)."""
        states = info.states
        if states is None or not bool(info.converged[0]) or getattr(self.ocp.model, "approximate_jacobians", False):
            return None
        d = self.ocp.disturbance
        nxt = np.asarray(states, dtype=np.float64).reshape(-1, self.horizon, self.ocp.nx)[0, 0]
        return nxt - d if d is not None else nxt.copy()

    @staticmethod
    def _shifted(U: np.ndarray) -> np.ndarray:
        """Warm start for the next solve: drop the applied input, repeat the last one."""
        return np.concatenate((U[1:], U[-1:]), axis=0)


def _array(v: np.ndarray | Tensor | Sequence) -> np.ndarray:
    """float64 numpy copy of an array, list or tensor (one that requires grad too: measurements are data)."""
    if isinstance(v, Tensor):
        v = v.detach().cpu()
    return np.array(v, dtype=np.float64)
