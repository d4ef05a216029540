"""What every controller kind shares: the closed loop's interface (Controller, StepStats) and the settings every
kind has (ControllerSettings, DisturbanceSettings), each field with its default, its check and its docstring.

A kind's own settings subclass ControllerSettings (the network NMPC's in controller/settings.py, the classical NMPC's
in controller/classical/settings.py) and register with the kind (pinnmpc.controller.registry); Hydra composes them
as the structured config behind conf/controller/<name>.yaml (group schema/controller). Fields are annotated Any for
Hydra: the check declared with each field is its type, so a bad value from the command line is that check's one line
naming the key (checked_settings), not a composition error.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, is_dataclass
from typing import Any, Protocol

import numpy as np

from pinnmpc.util import checks as c
from pinnmpc.util.checks import Dims, SettingError, setting


@dataclass
class StepStats:
    """What one OCP solve did, for metrics.json and debugging."""

    time_s: float
    iterations: int
    cost: float
    converged: bool
    fallback: bool


class Controller(Protocol):
    """What the closed loop needs of a controller (do-mpc style): make_step(x, x_ref) -> u and its statistics."""

    horizon: int
    stats: list[StepStats]

    @property
    def low(self) -> Any:
        """Input lower bounds (nu,)."""
        ...

    @property
    def high(self) -> Any:
        """Input upper bounds (nu,)."""
        ...

    def reset(self) -> None:
        """Forget warm starts and statistics: the start of a new run."""
        ...

    def make_step(self, x: np.ndarray, x_ref: np.ndarray) -> np.ndarray:
        """Input to apply now for the measured state x (nx,) and the next H reference states (H, nx)."""
        ...

    def describe(self) -> dict[str, Any]:
        """solver name and disturbance_gain, for metrics.json."""
        ...


def _limits(v: Any, _d: Dims) -> str | None:
    """null or a mapping (its keys are JointLimits' to check, controller/limits.py)."""
    ok = v is None or isinstance(v, Mapping) or is_dataclass(v)  # a JointLimits from a Python caller too
    return None if ok else "null or {low, high, weight, margin[, lookahead]}"


def _state_bounds(v: Any, dims: Dims) -> str | None:
    """null or one bound >= 0 per state."""
    return c.optional(c.vector("nx", c.real(0.0)))(v, dims)


@dataclass(kw_only=True)
class DisturbanceSettings:
    """Offset-free MPC (pinnmpc.controller.estimator): every predicted step gets an additive d, the last one-step
    prediction error filtered."""

    gain: Any = setting(0.7, check=c.real(0.0, 1.0))
    """0: off (the paper's controller); 1: d = the last error; in (0, 1): an exponential filter of it."""
    max_abs: Any = setting(None, check=_state_bounds)
    """Per-state bound on |d| (positions, velocities); null: unbounded (the configs: system.control.disturbance_max)."""
    notch: Any = setting(None, check=c.optional(c.boolean()))
    """Average the last two prediction errors before the filter: an error that flips sign every sample (a robot's
    stick-slip seen at the control rate) stays out of d, a lasting one enters half a sample later; null: the kind's
    choice (the network NMPC: on for a network fine-tuned on robot logs; the classical NMPC: off)."""


@dataclass(kw_only=True)
class ControllerSettings:
    """What every controller kind has: the horizon, the cost's weights, the input box, the joint limits, the warm
    start and the offset-free estimator (`controller.<field>=value`)."""

    kind: Any = setting("pinn", check=c.text())
    """The registered controller kind that builds from these settings (pinnmpc.controller.registry)."""
    horizon: Any = setting(5, check=c.whole(1))
    """Prediction horizon H (steps of tau)."""
    Q: Any = setting(check=c.weight("nx"))
    """State weight: diagonal (list of nx) or an nx x nx PSD matrix (the configs: system.control.Q)."""
    R: Any = setting(check=c.weight("nu"))
    """Input weight: diagonal (list of nu) or an nu x nu PSD matrix (the configs: system.control.R)."""
    R_rate: Any = setting(None, check=c.optional(c.weight("nu")))
    """Input-rate weight on u_k - u_{k-1} (diagonal or matrix); null: off (the configs: system.control.R_rate)."""
    u_low: Any = setting(None, check=c.optional(c.vector("nu")))
    """Input lower bounds; null: the model's input box (the network's training box, the system's)."""
    u_high: Any = setting(None, check=c.optional(c.vector("nu")))
    """Input upper bounds; null: the model's input box."""
    joint_limits: Any = setting(None, check=_limits)
    """Soft joint position limits on every predicted state, {low, high, weight, margin, lookahead}; null: none (the
    configs: system.control.joint_limits; docs/design.md, NMPC)."""
    warm_start: Any = setting(True, check=c.boolean())
    """Start each solve from the previous solution shifted by one step."""
    disturbance: DisturbanceSettings = setting(factory=DisturbanceSettings)
    """The offset-free estimator."""

    def make_consistent(self) -> None:
        """The checks across fields, once every field passed its own."""
        if (
            self.u_low is not None
            and self.u_high is not None
            and any(lo > hi for lo, hi in zip(self.u_low, self.u_high))
        ):
            raise SettingError(
                f"controller.u_low={list(self.u_low)} exceeds controller.u_high={list(self.u_high)}: expected low <= "
                "high in every entry"
            )


def checked_settings(cls: type[ControllerSettings], values: Any, dims: Dims) -> ControllerSettings:
    """A kind's settings from a config node, a dict or an instance, every field checked for an arm of dims
    ({nx, nu}): a bad value, a misspelt or a missing key is one line naming `controller.<key>`."""
    settings = c.settings_from(cls, values, "controller")
    if not isinstance(settings, cls):
        raise SettingError(f"controller settings of type {type(settings).__name__}; expected {cls.__name__}")
    c.check_fields("controller", settings, dims)
    settings.make_consistent()
    return settings
