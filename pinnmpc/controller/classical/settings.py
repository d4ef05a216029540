"""The classical NMPC's settings (`controller=casadi`, kind casadi): what every kind has (ControllerSettings) plus
the transcription, CasADi's solvers and their options, the real-time iteration and the C build; each field with its
default, check and docstring. `python -m pinnmpc.closed_loop controller=casadi --cfg job -p controller` prints them."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from pinnmpc.controller.base import ControllerSettings, DisturbanceSettings
from pinnmpc.util import checks as c
from pinnmpc.util.checks import SettingError, setting

TRANSCRIPTIONS = ("rk4", "radau", "network")  # controller.transcription: RK4 shooting, Radau IIA collocation or
#   a trained network's exported flow map
PLUGINS = ("ipopt", "sqpmethod", "fatrop")  # controller.solver: CasADi nlpsol plugins
QP_SOLVERS = ("qrqp", "hpipm", "osqp")  # controller.qpsol: CasADi conic plugins
OPT_LEVELS = ("-O0", "-O1", "-O2", "-O3", "-Os")  # controller.codegen_opt


def _options(v: Any, _d: Any) -> str | None:
    """A mapping of plugin names to their options (CasADi checks the options themselves)."""
    ok = isinstance(v, dict) and all(isinstance(o, dict) or o is None for o in v.values())
    return None if ok else "a mapping of plugin names to their options"


def _qp_options() -> dict[str, Any]:
    """Each QP solver's options (CasADi's conic plugin options)."""
    return {
        # error_on_fail false: a failed QP ends the SQP with a status (then the controller falls back), not an exception
        "qrqp": {"print_iter": False, "print_header": False, "error_on_fail": False},
        # inf: CasADi gives HPIPM every variable a box, an infinite bound becomes this (CasADi's 1e8 left a Panda
        # QP's interior point at its minimum step, unsolved); mode robust: its tolerances give SQP steps as accurate
        # as qrqp's (balance's stop 1e-4 off on a Panda QP, speed's short of a solution)
        "hpipm": {"error_on_fail": False, "inf": 1.0e6, "hpipm": {"mode": "robust"}},
        # ADMM converges slowly to tight tolerances: a high iteration cap
        "osqp": {
            "error_on_fail": False,
            "osqp": {"verbose": False, "eps_abs": 1e-10, "eps_rel": 1e-10, "max_iter": 10000},
        },
    }


def _nlp_options() -> dict[str, Any]:
    """Options passed to casadi.nlpsol for each solver (CasADi's and the plugin's own names)."""
    return {
        # tol: on the scaled KKT error; max_iter: a solve that hits it falls back; mu_init small: warm starts are close
        "ipopt": {"ipopt": {"tol": 1e-8, "max_iter": 100, "mu_init": 1e-3}},
        # its QP solver is qpsol/qpsols; max_iter_ls: backtracking steps per iteration (with 3 the iterates of a start
        # 0.5 rad off planar3's reference cycled); converged when the defects are below tol_pr and the Lagrangian's
        # gradient max-norm below tol_du
        "sqpmethod": {"max_iter": 20, "max_iter_ls": 8, "tol_pr": 1e-8, "tol_du": 1e-8},
        "fatrop": {"fatrop": {"tol": 1e-8, "max_iter": 100, "mu_init": 1e-3}},
    }


def _estimator_off() -> DisturbanceSettings:
    """The classical NMPC's offset-free estimator: off unless asked (the configs: the arm's
    system.control.casadi.disturbance_gain); null notch: off, on while the plant runs a period late."""
    return DisturbanceSettings(gain=0.0, notch=None)


@dataclass(kw_only=True)
class ClassicalSettings(ControllerSettings):
    """Classical NMPC on the true model (pinnmpc.controller.classical.nmpc): the same cost, bounds, limits and
    horizon as the network NMPC; the model transcribed by RK4 shooting or Radau IIA collocation, solved by CasADi."""

    kind: Any = setting("casadi", check=c.one_of("casadi"))
    """casadi: this kind (controller=casadi)."""
    disturbance: DisturbanceSettings = setting(factory=_estimator_off)
    """The offset-free estimator: off by default here (gain 0; the notch only while the plant runs late)."""
    solver: Any = setting("sqpmethod", check=c.one_of(*PLUGINS))
    """ipopt | sqpmethod | fatrop (CasADi nlpsol plugins); their options are solvers.<name>."""
    solvers: dict[str, Any] = setting(factory=_nlp_options, check=_options)
    """Options passed to casadi.nlpsol per plugin (controller.solvers.sqpmethod.max_iter=30)."""
    transcription: Any = setting("rk4", check=c.one_of(*TRANSCRIPTIONS))
    """rk4: multiple shooting over RK4 sub-steps (rk4_steps) | radau: Radau IIA collocation, the stage accelerations
    unknowns of the residual M(q) a + h(q, v) - tau(q, v, u) = 0 (no M^-1) | network: multiple shooting on a trained
    network's exported flow map (`network`), the way a CasADi user runs it."""
    network: Any = setting(None, check=c.optional(c.text()))
    """transcription=network: the surrogate (.pt or training .ckpt); null: the network shipped for the arm."""
    collocation_stages: Any = setting(3, check=c.whole(1))
    """radau: points per interval (order 2 * stages - 1)."""
    collocation_intervals: Any = setting(1, check=c.whole(1))
    """radau: intervals per tau."""
    qpsol: Any = setting("qrqp", check=c.one_of(*QP_SOLVERS))
    """QP solver of sqpmethod and of the real-time iteration: qrqp (active set, built in) | hpipm (interior point on
    the OCP's stage structure, Riccati recursion) | osqp (ADMM)."""
    qpsols: dict[str, Any] = setting(factory=_qp_options, check=_options)
    """Each QP solver's options (CasADi's conic plugin options)."""
    hessian: Any = setting("gauss_newton", check=c.one_of("gauss_newton", "exact"))
    """gauss_newton: the cost's Hessian only (constant, convex QPs) | exact: with the dynamics' curvature."""
    rk4_steps: Any = setting(None, check=c.optional(c.whole(1)))
    """rk4: sub-steps per tau in the prediction model; null: the fewest stable on the state box."""
    coulomb_width: Any = setting(None, check=c.optional(c.positive()))
    """rad/s: a failed solve is repeated on the model with sign(v) friction smoothed as tanh(v / width); only arms
    with a sign(v) term (the PowerCube); null: no repeat (the configs: system.control.coulomb_width)."""
    keep_unconverged: Any = setting(True, check=c.boolean())
    """A solve that does not converge still applies its inputs when, simulated through the model, they cost less
    than the previous plan's (counted unconverged, not a fallback); false: the previous plan, shifted."""
    rti: Any = setting(False, check=c.boolean())
    """Real-time iteration: one Gauss-Newton step per sample from the shifted solution, on the QP with the
    collocation's accelerations eliminated (classical/rti.py); the first sample, and any after a fallback, solves
    fully (needs solver=sqpmethod, hessian=gauss_newton)."""
    rti_limit_steps: Any = setting(2, check=c.whole(0))
    """Real-time iteration: more steps, each from the last, in a sample whose plan reaches where a joint-limit
    penalty acts (it switches on and off there, which one step does not follow); 0: none."""
    codegen: Any = setting(True, check=c.boolean())
    """Generate C for the solver's functions and compile them (cached by source hash)."""
    codegen_opt: Any = setting("-O2", check=c.one_of(*OPT_LEVELS))
    """C optimisation level of that code: lower levels compile a 7-joint arm's large generated code sooner and
    solve slower (compiled once, cached)."""

    def make_consistent(self) -> None:
        """The real-time iteration takes Gauss-Newton SQP steps."""
        super().make_consistent()
        if self.rti and self.solver != "sqpmethod":
            raise SettingError(
                f"rti=true takes one SQP step per sample: it needs solver=sqpmethod, got {self.solver!r}"
            )
        if self.rti and self.hessian != "gauss_newton":
            raise SettingError(
                f"rti=true takes Gauss-Newton steps: it needs hessian=gauss_newton, got {self.hessian!r}"
            )
