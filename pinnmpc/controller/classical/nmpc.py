"""The classical NMPC on the true model (CasADi nlpsol, compiled): the baseline the PINN controller is compared with.

Same cost, soft joint limits, bounds, horizon and zero-order hold as NMPC (pinnmpc.controller.nmpc), the same
make_step/reset/stats interface, the same fallback (a failed solve applies the previous plan shifted) and the same
offset-free estimator. The model is transcribed by RK4 shooting (pinnmpc.controller.classical.ocp) or Radau IIA
collocation (pinnmpc.controller.classical.collocation); a real-time iteration takes one condensed Gauss-Newton step per
sample (pinnmpc.controller.classical.rti).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from pinnmpc.controller.base import StepStats, checked_settings
from pinnmpc.controller.classical.network_ocp import NetworkOCP
from pinnmpc.controller.classical.ocp import CasadiOCP, NlpSolver, Solution, merged
from pinnmpc.controller.classical.rti import RTI_STATUS, RtiSolver, rti_function, rti_solver
from pinnmpc.controller.classical.settings import ClassicalSettings
from pinnmpc.controller.estimator import OffsetFree, late_notch
from pinnmpc.plant.stick_slip import coulomb_joints
from pinnmpc.systems.settings import system_dims

RTI_STATUSES = {"Solve_Succeeded", "Maximum_Iterations_Exceeded", RTI_STATUS}  # one step's usable ends


class CasadiNMPC:
    """Receding-horizon control: solve the OCP from the shifted last solution, apply the first input."""

    def __init__(
        self,
        ocp: CasadiOCP,
        solver: NlpSolver | RtiSolver,
        label: str,
        warm_start: bool = True,
        rti: bool = False,
        cold_solver: NlpSolver | None = None,
        disturbance_gain: float = 0.0,
        disturbance_max: Sequence[float] | None = None,
        disturbance_notch: bool = False,
        smooth_solver: NlpSolver | None = None,
        keep_unconverged: bool = True,
        rti_limit_steps: int = 2,
        notch_when_late: bool = False,
    ) -> None:
        self.ocp, self.solver, self.label = ocp, solver, label
        self.horizon, self.nx, self.nu = ocp.horizon, ocp.nx, ocp.nu
        self.low, self.high = ocp.low.copy(), ocp.high.copy()
        self.warm_start, self.rti = bool(warm_start), bool(rti)
        self.cold_solver = cold_solver or solver  # RTI: a full solve while there is no solution to iterate from
        self.smooth_solver = smooth_solver  # the same OCP with sign(v) friction smoothed: tried when a solve fails
        self.keep_unconverged = bool(keep_unconverged)  # an unconverged solve's inputs against the previous plan
        if isinstance(rti_limit_steps, bool) or not isinstance(rti_limit_steps, int) or rti_limit_steps < 0:
            raise ValueError(f"controller.rti_limit_steps={rti_limit_steps!r}; expected a whole number >= 0")
        self.rti_limit_steps = rti_limit_steps  # RTI: more steps per sample where a plan is at the joint limits
        self.disturbance_gain = float(disturbance_gain)
        self.delay_periods = 0  # 1: each input runs a period after its state (the closed loop sets it): plan ahead
        self._estimator = OffsetFree(self.nx, self.disturbance_gain, disturbance_max, disturbance_notch)
        self.disturbance_notch, self.notch_when_late = bool(disturbance_notch), bool(notch_when_late)
        self.stats: list[StepStats] = []
        self.reset()

    def describe(self) -> dict[str, Any]:
        """Solver, offset-free gain and what predicts (the true model), for metrics.json and headlines."""
        return {
            "controller": "casadi",
            "solver": self.label,
            "disturbance_gain": self.disturbance_gain,
            "disturbance_notch": self._estimator.notch,
            "prediction": "true_model",
            "real_time": self.rti,  # one SQP step per sample: unconverged by design
            **self.ocp.describe(),  # the transcription and its settings
            "smoothed_solves": self.smoothed_solves,  # failed solves repeated on the smoothed-friction model
        }

    def reset(self) -> None:
        """Forget the warm start, the last applied input, the disturbance estimate and the statistics."""
        self._U = self._cold_inputs()
        self._u_prev = self._U[0].copy()
        self._w: np.ndarray | None = None  # the last solution shifted (None: cold start from the measured state)
        self._lam: tuple[np.ndarray, np.ndarray] | None = None  # its multipliers shifted (None: zeros)
        self._last: tuple | None = None  # the last measured state, the input applied and the plan's unknowns (or None)
        self._predicted: np.ndarray | None = None  # the model's undisturbed x after them, where already computed
        self._estimator.notch = late_notch(self.disturbance_notch, self.notch_when_late, self.delay_periods)
        self._estimator.reset()
        self.stats = []
        self.smoothed_solves = 0

    def _cold_inputs(self) -> np.ndarray:
        """Zero inputs projected onto the box, (H, nu)."""
        return np.clip(np.zeros((self.horizon, self.nu)), self.low, self.high)

    @property
    def plan(self) -> np.ndarray:
        """The inputs the next solve starts from (the last plan shifted by one step), (H, nu)."""
        return self._U.copy()

    def make_step(self, x: np.ndarray, x_ref: np.ndarray) -> np.ndarray:
        """Input to apply now, given the measured state (nx,) and the next H reference states (H, nx)."""
        x0 = np.asarray(x, dtype=np.float64).reshape(-1)
        ref = np.asarray(x_ref, dtype=np.float64)
        if x0.shape != (self.nx,):
            raise ValueError(f"the state must have {self.nx} entries, got shape {np.shape(x)}")
        if ref.shape != (self.horizon, self.nx):
            want = (self.horizon, self.nx)
            raise ValueError(f"x_ref must cover the horizon: expected {want[0]} x {want[1]}, got {ref.shape}")
        if self.ocp.joint_limits is not None:
            ref = self.ocp.joint_limits.governed(ref)
        start = time.perf_counter()
        sol: Solution | None = None
        ahead = None
        try:
            self._estimate_disturbance(x0)
            if self.delay_periods:  # plan from the state the input will meet: the running input's prediction
                guess = self._last[2] if self._last is not None else None
                ahead = (self.solver.flow(x0, self._u_prev, guess), guess)
                d = self._estimator.value if self._estimator.on else None
                x0_plan = ahead[0] if d is None else ahead[0] + d
            else:
                x0_plan = x0
            solver = self.solver if self._w is not None else self.cold_solver
            self._load(solver, x0_plan, ref)
            sol = solver()
            ok = self._usable(sol, rti=solver is self.solver and self.rti)
            if ok and solver is self.solver and self.rti and self._at_limits(sol):
                sol, ok = self._limit_steps(sol)
            if not ok and self.smooth_solver is not None:  # e.g. sign(v) friction at rest: no smooth NLP solution
                iterations = sol.iterations
                solver = self.smooth_solver
                self._load(solver, x0_plan, ref)
                sol = solver()
                sol.iterations += iterations
                ok = self._usable(sol, rti=False)
                self.smoothed_solves += 1
            kept_cost = None if ok or not self.keep_unconverged else self._kept_cost(sol, solver.p)
        except (RuntimeError, FloatingPointError, np.linalg.LinAlgError):  # e.g. an evaluation error on NaN
            ok, kept_cost = False, None
        kept = kept_cost is not None
        if ok or kept:
            U = np.clip(sol.w[self.ocp.iu], self.low, self.high)  # an interior point may overshoot by 1e-8
        else:  # self._U is the previous plan shifted: its first entry is the input planned for now
            U = np.clip(np.nan_to_num(self._U, nan=0.0, posinf=0.0, neginf=0.0), self.low, self.high)
        elapsed = time.perf_counter() - start
        self._shift(sol if ok or kept else None, U)
        running = self._u_prev  # the input the plant holds over the coming period when it runs a period late
        self._u_prev = U[0].copy()
        guess = sol.w[self.ocp.iz[0]].copy() if (ok or kept) and self.ocp.nz else None  # the plan's unknowns
        if self.delay_periods:
            self._last = (x0.copy(), running, guess)  # guess: for the input planned now, the next sample's running one
            self._predicted = None if ahead is None else ahead[0]
        else:
            self._last, self._predicted = (x0.copy(), self._u_prev, guess), None
        self.stats.append(
            StepStats(
                time_s=elapsed,
                iterations=sol.iterations if sol is not None else 0,
                cost=sol.cost if ok else kept_cost if kept else float("nan"),
                converged=bool(ok and sol.success),
                fallback=not (ok or kept),
            )
        )
        return U[0].copy()

    def _limit_steps(self, sol: Solution) -> tuple[Solution, bool]:
        """rti_limit_steps more real-time steps, each from the last: the soft joint limits' penalty switches on and
        off at the limits, which one step from the last linearisation does not follow (plans crossed them)."""
        ok = True
        for _ in range(self.rti_limit_steps):
            iterations = sol.iterations
            self.solver.w0[:] = sol.w
            sol = self.solver()
            sol.iterations += iterations
            ok = self._usable(sol, rti=True)
            if not ok:
                break
        return sol, ok

    def _at_limits(self, sol: Solution) -> bool:
        """Whether the last plan or this solve's states reach where a joint-limit penalty acts."""
        limits, states = self.ocp.joint_limits, self.ocp.ix[1:]
        if limits is None or not limits.joints.size:
            return False
        plans = [sol.w] if self._w is None else [sol.w, self._w]
        return any(bool(limits.reached(np.asarray(w)[states][None])[0]) for w in plans)

    @staticmethod
    def _usable(sol: Solution, rti: bool) -> bool:
        """A solve counts when the solver succeeded (RTI: took its one step) and everything is finite."""
        if not (sol.success or (rti and sol.status in RTI_STATUSES)):
            return False
        return bool(np.isfinite(sol.w).all() and np.isfinite(sol.cost))

    def _kept_cost(self, sol: Solution, p: np.ndarray) -> float | None:
        """The cost of an unconverged solve's inputs simulated through the model, when it is below the previous plan's
        (far off the reference Gauss-Newton SQP converges linearly: its iterate at the cap is usually far better);
        None when it is not, or when the iterate (the next warm start) is not finite."""
        if not all(np.isfinite(a).all() for a in (sol.w, sol.lam_x, sol.lam_g)):
            return None
        plan = np.clip(np.nan_to_num(self._U, nan=0.0, posinf=0.0, neginf=0.0), self.low, self.high)
        U = np.clip(sol.w[self.ocp.iu], self.low, self.high)
        mine, theirs = (self.ocp.rollout_cost(u, p) for u in (U, plan))
        return mine if np.isfinite(mine) and not mine >= theirs else None

    def _load(self, s: NlpSolver | RtiSolver, x0: np.ndarray, ref: np.ndarray) -> None:
        """Parameters and starting point into the solver's input buffers."""
        ocp = self.ocp
        s.p[ocp.p_x0] = x0
        s.p[ocp.p_ref] = ref.reshape(-1)
        s.p[ocp.p_uprev] = self._u_prev
        s.p[ocp.p_d] = 0.0 if self.disturbance is None else self.disturbance
        if self._w is None:  # cold: every state at the measured one, the planned (or zero) inputs
            ocp.cold_start(s.w0, x0, self._U, self._u_prev)
        else:
            s.w0[:] = self._w
            ocp.pin_start(s.w0, x0, self._u_prev)  # the initial-state constraints hold at the start
        if self._lam is None:
            s.lam_x0[:] = 0.0
            s.lam_g0[:] = 0.0
        else:
            s.lam_x0[:], s.lam_g0[:] = self._lam

    def _shift(self, sol: Solution | None, U: np.ndarray) -> None:
        """Warm start for the next step: the solution (primal and dual) moved one stage forward, the last stage
        repeated. After a fallback only the inputs are kept (shifted again) and the states restart cold."""
        if not self.warm_start:
            self._U, self._w, self._lam = self._cold_inputs(), None, None
            return
        self._U = np.concatenate((U[1:], U[-1:]), axis=0)
        if sol is None:
            self._w, self._lam = None, None
            return
        ocp = self.ocp
        nw = ocp.shifted(sol.w, ocp.w_blocks)
        nw[ocp.iu] = self._U
        self._w, self._lam = nw, (ocp.shifted(sol.lam_x, ocp.w_blocks), ocp.shifted(sol.lam_g, ocp.g_blocks))

    @property
    def disturbance(self) -> np.ndarray | None:
        """The disturbance the next solve predicts with (None: off or not estimated yet)."""
        return self._estimator.value

    def applied_input(self, u: np.ndarray) -> None:
        """The input the plant sent in place of the last one planned (a robot's safety layer clipped it): the next
        solve's u_{-1}, and the one its prediction and estimate start from."""
        self._u_prev = np.array(u, dtype=np.float64)
        if self._last is not None and not self.delay_periods:
            self._last, self._predicted = (self._last[0], self._u_prev, self._last[2]), None

    def prediction_error(self, x_prev: np.ndarray, u_prev: np.ndarray, x: np.ndarray) -> np.ndarray:
        """x - F(x_prev, u_prev) of the model this controller predicts with (undisturbed): the model monitor's
        one-step miss, as the network NMPC's (metrics.json's model_monitor and model_fits)."""
        flow = self.solver.flow(np.asarray(x_prev, dtype=np.float64), np.asarray(u_prev, dtype=np.float64))
        return np.asarray(x, dtype=np.float64) - flow

    def _estimate_disturbance(self, x: np.ndarray) -> None:
        """Offset-free MPC as NMPC's: what the model missed over the last period (x - F(x_prev, u_prev)),
        filtered by the gain and bounded by disturbance_max, is added to every predicted step."""
        if not self._estimator.on or self._last is None:
            return
        predicted = self._predicted if self._predicted is not None else self.solver.flow(*self._last)
        self._estimator.update(x - predicted)


def sqpmethod_options(cfg: ClassicalSettings, options: dict[str, Any]) -> dict[str, Any]:
    """sqpmethod's options with the QP solver controller.qpsol and its options from controller.qpsols (merged with
    those written for it under solvers.sqpmethod)."""
    named = options.get("qpsol")
    qpsol = cfg.qpsol
    qp_options = dict((cfg.qpsols or {}).get(qpsol) or {})
    if named == qpsol:  # options written for this QP solver under solvers.sqpmethod too
        qp_options = merged(qp_options, options.get("qpsol_options") or {})
    return {**options, "qpsol": qpsol, "qpsol_options": qp_options}


def build_casadi_nmpc(cfg: Any, system: Any) -> CasadiNMPC:
    """CasadiNMPC from its settings (ClassicalSettings, or a config node or dict of them: conf/controller/casadi.yaml),
    each checked; what a Python caller leaves out takes ClassicalSettings' default, as the commands do."""
    cfg = checked_settings(ClassicalSettings, cfg, system_dims(system))
    assert isinstance(cfg, ClassicalSettings)
    plugin, rti, transcription = cfg.solver, cfg.rti, cfg.transcription
    low = system.input_box.low if cfg.u_low is None else cfg.u_low
    high = system.input_box.high if cfg.u_high is None else cfg.u_high

    surrogate = None
    if transcription == "network":  # the network's flow map: loaded once, the smoothed repeat has no use for it
        from pinnmpc.surrogate.checkpoint import load_surrogate
        from pinnmpc.systems.previous_input import takes_previous_input

        surrogate = load_surrogate(cfg.network, system=system.name if cfg.network is None else None)
        dims = (len(system.state_names), len(system.input_names))
        if (surrogate.nx, surrogate.nu) != dims:
            raise ValueError(
                f"controller.network={cfg.network!r} maps {surrogate.nx} states and {surrogate.nu} inputs; the arm "
                f"{system.name} has {dims[0]} and {dims[1]}"
                + (
                    " (it takes the previous input too: only controller=nmpc runs such a network)"
                    if takes_previous_input(surrogate)
                    else ""
                )
            )

    def make_ocp(coulomb_width: float | None = None) -> CasadiOCP:
        """The OCP of these settings, on the exact model or with its sign(v) friction smoothed."""
        problem = (system, cfg.horizon, cfg.Q, cfg.R, cfg.R_rate, low, high)
        if transcription == "network":
            return NetworkOCP(surrogate, str(cfg.network or "shipped"), *problem, joint_limits=cfg.joint_limits)
        if transcription == "radau":
            from pinnmpc.controller.classical.collocation import RadauOCP

            stages, intervals = cfg.collocation_stages, cfg.collocation_intervals
            return RadauOCP(*problem, stages, intervals, joint_limits=cfg.joint_limits, coulomb_width=coulomb_width)
        steps = cfg.rk4_steps if coulomb_width is None else None
        return CasadiOCP(*problem, rk4_steps=steps, joint_limits=cfg.joint_limits, coulomb_width=coulomb_width)

    ocp = make_ocp()
    options = dict((cfg.solvers or {}).get(plugin) or {})
    if plugin == "sqpmethod":
        options = sqpmethod_options(cfg, options)
    hessian, codegen, level = cfg.hessian, cfg.codegen, cfg.codegen_opt
    extra = [rti_function(ocp)] if rti else []  # compiled with the solver's functions: their code is shared
    solver = ocp.solver(plugin, options, hessian, codegen, level, extra)
    smooth_solver, width = None, cfg.coulomb_width
    # RK4: its own sub-steps, the smoothed model is stiffer; a network has no sign(v) to smooth
    if width is not None and coulomb_joints(system) and transcription != "network":
        smooth_solver = make_ocp(float(width)).solver(plugin, options, hessian, codegen, level)
    cold_solver = None
    if rti:  # one Gauss-Newton step from the shifted solution; the first step (and any after a fallback) solves fully
        qp_data = solver.functions["rti_qp"]
        cold_solver, solver = solver, rti_solver(ocp, options["qpsol"], options["qpsol_options"], qp_data, solver.flow)
    d = cfg.disturbance
    label = f"casadi-{plugin}"
    label += f"-{options['qpsol']}" if plugin == "sqpmethod" and options["qpsol"] != "qrqp" else ""
    label += f"-{transcription}" if transcription != "rk4" else ""
    return CasadiNMPC(
        ocp,
        solver,
        label=label + ("-rti" if rti else ""),
        warm_start=cfg.warm_start,
        rti=rti,
        cold_solver=cold_solver,
        disturbance_gain=float(d.gain),
        disturbance_max=d.max_abs,
        disturbance_notch=bool(d.notch),  # null: off, on while the plant runs a period late
        notch_when_late=d.notch is None,
        smooth_solver=smooth_solver,
        rti_limit_steps=cfg.rti_limit_steps,
        keep_unconverged=cfg.keep_unconverged,
    )
