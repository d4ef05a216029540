"""The network NMPC's settings (`controller=nmpc`, `controller=exact`: kind pinn): what every kind has
(ControllerSettings) plus the solver and what the OCP predicts with; each field with its default, check and docstring.
`python -m pinnmpc.closed_loop --cfg job -p controller` prints them as composed."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from pinnmpc.controller.base import ControllerSettings
from pinnmpc.controller.solvers import SOLVERS
from pinnmpc.controller.solvers.lifted import valid_trust
from pinnmpc.util import checks as c
from pinnmpc.util.checks import SettingError, setting

MODELS = ("surrogate", "exact_values", "prior")  # controller.model: what the OCP predicts with
GAUSS_NEWTON = ("lifted_gauss_newton", "gauss_newton")  # the solvers that take a numpy model's Jacobians


def _solver_options(v: Any, _d: Any) -> str | None:
    """A mapping of solver name to its options (each solver's dataclass checks its own)."""
    ok = isinstance(v, dict) and all(k in SOLVERS and (o is None or isinstance(o, dict)) for k, o in v.items())
    return None if ok else f"a mapping of solver names ({', '.join(SOLVERS)}) to their options"


def _trust(v: Any, _d: Any) -> str | None:
    """null or a fraction of the input box's width > 0 (inf: no bound)."""
    return None if v is None or valid_trust(v) else "a fraction of the input box's width > 0 or null"


@dataclass(kw_only=True)
class NetworkSettings(ControllerSettings):
    """NMPC on the network (pinnmpc.controller.nmpc): the paper's horizon and cost solved by a gradient method on the
    flow map; the paper's own controller is solver=rmsprop disturbance.gain=0 (the defaults: Gauss-Newton,
    offset-free)."""

    kind: Any = setting("pinn", check=c.one_of("pinn"))
    """pinn: this kind (controller=nmpc, controller=exact)."""
    solver: Any = setting("lifted_gauss_newton", check=c.one_of(*SOLVERS))
    """lifted_gauss_newton (fastest) | gauss_newton | rmsprop (the paper's) | lbfgs; its settings are
    solvers.<name> (pinnmpc/controller/solvers/)."""
    solvers: dict[str, Any] = setting(factory=dict, check=_solver_options)
    """Each solver's settings (controller.solvers.<name>.<field>=value; the configs compose every solver's
    dataclass here); a solver not named takes its dataclass's defaults."""
    model: Any = setting("surrogate", check=c.one_of(*MODELS))
    """What the OCP predicts with: surrogate (the network replaces integration: the paper's controller) |
    exact_values (the true model, integrated by compiled RK4, gives the predicted states and the network only
    their Jacobians; Gauss-Newton solvers) | prior (the network's physics prior alone: what the network adds)."""
    exact_rk4_steps: Any = setting(None, check=c.optional(c.whole(1)))
    """exact_values: RK4 sub-steps per tau; null: the fewest stable on the state box (as the classical NMPC's)."""
    rti: Any = setting(None, check=c.optional(c.boolean()))
    """The real-time iteration (solver=lifted_gauss_newton): rti_steps lifted steps per sample from the last plan's
    states, the first solve (and any after a fallback) full; null: on for a network trained on the model (or
    fine-tuned against an identified model), and with a trust bound for one fine-tuned on robot logs alone; false:
    every sample solved to convergence (controller/build.py real_time_default). The classical kind's key is the
    same (controller.rti)."""
    rti_trust: Any = setting(None, check=_trust)
    """The real-time iteration's trust bound for a network fine-tuned on robot logs: a step moving an input by more
    than this fraction of its box width is solved fully; null: none (the configs: system.control.rti_trust)."""
    R_rate_previous_input: Any = setting(None, check=c.optional(c.weight("nu")))
    """The input-rate weight for a network that takes the previous input (model.previous_input) where R_rate is
    null: with an actuator's lag in the model the horizon's last inputs barely move the tracked states, so without
    one the real-time steps swing them past the trust bound and half the samples are solved fully; null: none (the
    configs: system.control.R_rate_previous_input)."""

    def make_consistent(self) -> None:
        """A numpy prediction model needs a Gauss-Newton solver (its values are not differentiable by torch)."""
        super().make_consistent()
        if self.rti and self.solver != "lifted_gauss_newton":
            raise SettingError(
                f"controller.rti=true takes lifted steps: needs solver=lifted_gauss_newton, got {self.solver!r}"
            )
        given = (self.solvers.get(self.solver) or {}).get("rti") if self.solvers else None
        if given is not None:  # the solver's own field: the real-time iteration has one key, the controller's
            raise SettingError(
                f"controller.solvers.{self.solver}.rti={given!r}: set controller.rti={given} instead (the real-time "
                "iteration's one key, for every controller kind)"
            )
        if self.model != "surrogate" and self.solver not in GAUSS_NEWTON:
            raise SettingError(
                f"controller.model={self.model} needs a Gauss-Newton solver {list(GAUSS_NEWTON)} (its values are "
                f"numpy, not differentiable by torch), got controller.solver={self.solver!r}"
            )
