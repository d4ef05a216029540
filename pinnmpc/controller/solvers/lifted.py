"""Lifted (multiple-shooting) Gauss-Newton: all H network steps in one batched call per iteration.

The iteration lives here; the linearisation at the lifted states is pinnmpc.controller.shooting's, the step
within the box pinnmpc.controller.box_step's.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from pinnmpc.controller.array_backend import Array, Nd, read_only
from pinnmpc.controller.box_step import newton_step
from pinnmpc.controller.compiled_rti import CompiledRti, compiled_step, step_flops
from pinnmpc.controller.ocp import HorizonOCP
from pinnmpc.controller.shooting import linearise, reached
from pinnmpc.controller.solvers.base import NO_WARM, NoWarm, Problem, SolveInfo, SolveResult, project, result
from pinnmpc.controller.solvers.gauss_newton import GaussNewtonSolver

COMPILED_STEPS: dict[tuple, CompiledRti] = {}  # per (horizon, sizes, damping, limits, weights): the compiled step
STEP_OF: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # per OCP and solver choice: its step (None: numpy)


@dataclass(frozen=True, eq=False)
class LiftedWarm:
    """The lifted solver's receding-horizon warm start: the states x_1..x_H the last solution reaches.

    One step on they are the next problem's lifted states s_1..s_{H-1}, so the first iteration needs no
    rollout (H sequential network calls) to start from.
    """

    states: np.ndarray  # (B, H, nx)
    reached: bool | None = None  # whether they meet the OCP's joint-limit penalty, where the step that planned them
    #   said so (compiled_step); None: not known


@dataclass
class LiftedGaussNewtonSolver(GaussNewtonSolver):
    """Gauss-Newton on the lifted (multiple-shooting) problem, condensed back to the inputs.

    The states at the start of each horizon step are extra unknowns: every iteration evaluates the
    network and its Jacobians at all H steps in one batched call instead of H sequential ones,
    condenses the linearised dynamics into a Gauss-Newton step on U (the defects ride along as
    offsets) and moves the states to the linearised prediction. At convergence the defects vanish,
    so the solution is that of the single-shooting problem. The states start from the last solve's
    predicted trajectory, one step on, when the controller hands it back as LiftedWarm (a receding-horizon
    warm start that costs no rollout); otherwise from a rollout of U0. Falls back to single-shooting
    Gauss-Newton when it does not converge, ends worse than it began, or ends above the cost its model promised
    (then the decreases its stopping tests trusted were the model's, not the cost's).
    """

    warm_type: ClassVar[type] = LiftedWarm  # the states its solution reaches, one step on
    warm_field: ClassVar[str] = "states"
    tol_defect: float = 1e-10
    """Converged also needs every state defect F(s_i, u_i) - s_{i+1} below this."""
    fast_ratio: float = 1e-3
    """Two full steps in a row, the latest cutting the predicted decrease below this x the one before: the
    superlinear phase, extrapolated from that ratio alone (0: always from two ratios)."""
    lifted_max_iter: int = 5
    """Lifted iterations; an unconverged problem (saturated inputs, slow) then goes to single shooting with
    max_iter more."""
    tol_final_defect: float = 1e-8
    """The final states come from one batched call plus the last linearisation where every defect is below
    this, else from a full rollout."""
    warm_max_iter: int = 10
    """max_iter for a warm-started solve (every sample after the first): the next sample goes on from its plan, and
    the cap keeps a solve within the control period where a fine-tuned network's learnt stick-slip makes Gauss-Newton
    crawl (docs/results.md); a cold solve keeps max_iter."""
    rti: bool | None = None
    """Real-time iteration: rti_steps lifted steps per sample from the last plan's states, no convergence test
    (the first solve, and any after a fallback, solves fully): the counterpart of the classical rti. null (auto):
    the controller decides from its model (pinnmpc.controller.build.real_time_default); false: every sample
    solved to convergence; a solver built without a controller treats null as false."""
    rti_steps: int = 1
    """Lifted steps per sample of the real-time iteration (more: closer to converged, slower)."""
    rti_trust: float | None = None
    """A real-time step that moves any input by more than this fraction of its box width is not trusted: that sample
    is solved to convergence from where the step got to (the iteration's Gauss-Newton model was far off there).
    null (auto): the controller decides from its model (pinnmpc.controller.build.trust_default: the arm's
    system.control.rti_trust for a network fine-tuned on robot logs, every step trusted otherwise); inf: every step
    trusted; a solver built without a controller treats null as inf."""
    cold_states: str = "reference"
    """Where a cold solve's lifted states start (the first sample, any after a fallback): reference (the reference's
    states, as multiple-shooting codes start: the horizon's nonlinearity spread over its nodes, so long horizons
    converge in a few lifted steps) | rollout (of U0 from x0)."""
    cold_max_iter: int = 10
    """Lifted iterations of a cold solve run to convergence (lifted_max_iter for the others): from the reference's
    states and node_inputs a horizon of 40 converges in 2-3; one holding a jump the arm cannot make cycles, damped
    (cycle_step), to within a millionth of its optimal cost in about 10."""
    cold_accept: bool = True
    """A real-time iteration's cold solve takes at most cold_rti_max_iter lifted iterations and hands on its plan,
    converged or not, and whether or not its cost keeps the model's promise, where that ends below its start's cost
    (the next samples' steps go on from it), so its cold start is bounded in iterations; false, or a solver run to
    convergence (rti false): cold_max_iter, then single shooting with max_iter more."""
    cold_rti_max_iter: int = 5
    """Lifted iterations of a real-time iteration's cold solve (cold_accept): a jump the arm cannot make at H = 40
    takes up to 10 to converge, and the closed loop tracks the same from the plan after 5 (docs/results.md)."""
    cycle_step: float = 0.5
    """A lifted step that turns back on the last one (cosine below -1/2: full steps cycling between two points, as
    where an infeasible jump in the reference keeps inputs on and off their bounds) goes this fraction of the way,
    which damps the cycle out; other steps stay full (1: full steps always)."""
    tol_promise_inexact: float = 1e-3
    """controller.model=exact_values: relative slack of the check that a stop's cost keeps the model's promise
    (the Jacobians are the PINN's, not the derivatives of the values, so promises are inexact)."""
    lifted_max_iter_inexact: int = 20
    """controller.model=exact_values, or a prior whose Jacobian stands in: lifted_max_iter for it (inexact Jacobians
    converge linearly); a real-time iteration's cold solve keeps cold_rti_max_iter (cold_accept)."""
    compiled_step: bool = True
    """A real-time step of one problem runs its work after the network call (the chain, the Gauss-Newton model, the
    box step) as one compiled function (pinnmpc.controller.compiled_rti, CasADi-generated C, built once per horizon
    and weights) where that is small (compiled_max_flops); false: in numpy. The same arithmetic, to rounding."""
    compiled_max_flops: float = 3.0e5
    """The largest step (multiply-adds, compiled_rti.step_flops) compiled: beyond it numpy's BLAS is the faster
    (docs/results.md, section 6)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.cold_states not in ("reference", "rollout"):
            raise ValueError(f"LiftedGaussNewtonSolver.cold_states={self.cold_states!r}; expected reference or rollout")
        if not 0 < self.cycle_step <= 1:
            raise ValueError(f"LiftedGaussNewtonSolver.cycle_step={self.cycle_step!r}; expected a fraction in (0, 1]")
        for name in ("rti_steps", "lifted_max_iter", "lifted_max_iter_inexact", "cold_max_iter", "cold_rti_max_iter"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"LiftedGaussNewtonSolver.{name}={value!r}; expected a whole number >= 1")
        trust = self.rti_trust
        if trust is not None and not valid_trust(trust):
            raise ValueError(
                f"LiftedGaussNewtonSolver.rti_trust={trust!r}; expected a fraction of the input box's width > 0 "
                "(inf: every step trusted) or null"
            )

    def solve(
        self, problem: Problem, U0: Array, warm: LiftedWarm | NoWarm = NO_WARM
    ) -> tuple[Array, SolveInfo, LiftedWarm | NoWarm]:
        """Optimised inputs, statistics (with the states they reach) and those states as the next warm start."""
        return super().solve(problem, U0, warm)

    @staticmethod
    def _next_warm(out: np.ndarray | None) -> tuple[LiftedWarm | NoWarm, np.ndarray | None]:
        """The states the solution reaches: the next solve's warm start, and the plan's prediction for NMPC."""
        return (NO_WARM if out is None else LiftedWarm(out)), out

    def _solve(self, ocp: HorizonOCP, *problem: Nd | None, stepped: tuple[Nd, Nd, Nd] | None = None) -> SolveResult:
        """Lifted iterations on the numpy surrogate; single shooting when there is none or they fail. problem: x0,
        U0, x_ref, u_prev, low, high and prior as GaussNewtonSolver._solve takes them; stepped: the real-time step
        already taken from prior (warm_step's inputs, states and cost), not taken again."""
        x0, U0, x_ref, u_prev, low, high, prior = problem
        if ocp.flow is None:
            return (*super()._solve(ocp, x0, U0, x_ref, u_prev, low, high, None)[:4], None)
        shape, (horizon, nx, nu) = U0.shape, (ocp.horizon, ocp.nx, ocp.nu)
        n = horizon * nu
        x0b, refb = x0.reshape(-1, nx), x_ref.reshape(-1, horizon, nx)
        upb = u_prev.reshape(-1, nu)
        U = np.minimum(np.maximum(U0, low), high).reshape(-1, n)  # np.clip's values, without its Python wrapper
        lo, hi = _box_rows(shape, low, high)
        batch = U.shape[0]
        nodes = np.empty((batch, horizon, nx))  # s_0 = x0 (fixed), s_1..s_{H-1} lifted
        nodes[:, 0] = x0b
        done = 0  # steps already taken (a real-time iteration's)
        if prior is not None:  # the last plan's states x_2..x_H are this plan's s_1..s_{H-1}
            nodes[:, 1:] = prior[:, 1:]
            if self.rti:
                before = U
                U, states, cost = self._rti_steps(ocp, nodes, U, refb, upb, lo, hi) if stepped is None else stepped
                if self._keeps(ocp, prior, before, U, states, hi - lo):
                    unconverged = np.zeros(batch, dtype=bool)
                    return result(shape, U, np.full(batch, self.rti_steps, dtype=np.int64), cost, unconverged, states)
                # a step beyond rti_trust, or a plan at the soft joint limits (their penalty switches on and off
                # there, which steps from the last plan's linearisation do not follow: plans crossed the limits):
                # this sample is solved fully from where the steps got to
                nodes[:, 1:] = states[:, :-1]
                done += self.rti_steps
        elif self.cold_states == "reference":
            nodes[:, 1:] = refb[:, :-1]
            U = node_inputs(ocp, nodes, refb, U, lo, hi, self.damping)
        else:
            nodes[:, 1:] = ocp.rollout(x0b, U.reshape(-1, horizon, nu))[:, :-1]
        start_cost = None  # the model's cost of U0 at the first linearisation
        running = np.ones(batch, dtype=bool)
        iterations = np.full(batch, done, dtype=np.int64)
        predictions = np.full((batch, 2), np.nan)  # the two previous predicted decreases, latest first
        was_cut = np.ones(batch, dtype=bool)  # whether a bound cut the previous step short (none taken yet)
        promised = np.full(batch, np.inf)  # the model's cost of the point each problem stops at (after its step)
        inexact = getattr(ocp.flow, "approximate_jacobians", False)
        # a real-time iteration's cold plan is handed on however it stopped (cold_accept), within cold_rti_max_iter
        handed_on = bool(self.rti and self.cold_accept and prior is None)
        if handed_on:
            cap = self.cold_rti_max_iter
        elif inexact:
            cap = self.lifted_max_iter_inexact
        else:
            cap = self.cold_max_iter if prior is None else self.lifted_max_iter
        last_step = np.zeros_like(U)  # each problem's last step, against which a reversal shows a cycle
        for _ in range(cap):
            # the whole batch every time (no row gathering: batch-1 solves are dominated by per-op overhead);
            # problems that stopped take no further steps, their states only settle onto the prediction
            pred, sens, defect, steps = linearise(ocp, nodes, U)
            f, jtj, grad = ocp.gauss_newton_model(pred, sens, U, refb, upb)
            if start_cost is None:
                start_cost = f
            delta, pgrad_max, predicted, cut = newton_step(jtj, grad, U, lo, hi, self.damping)
            small = (pgrad_max < self.tol_grad) | (predicted <= self.tol_cost * f)
            go = running & ~(small & (defect <= self.tol_defect))
            # this step is the last when what remains after it, extrapolated from the model's predicted
            # decreases, is negligible: the cost reached is measured below
            last = self._remaining(predicted, predictions, ~(cut | was_cut)) <= self.tol_gap * f
            predictions[:, 1] = predictions[:, 0]
            predictions[:, 0] = predicted
            was_cut = cut
            iterations += go
            step = np.where(go[:, None], np.clip(U + delta, lo, hi) - U, 0.0)
            # a step that turns back on the last one (cosine below -1/2) is the cycle: it goes cycle_step of the way
            turn = (step * last_step).sum(-1)
            back = turn < -0.5 * np.linalg.norm(step, axis=-1) * np.linalg.norm(last_step, axis=-1)
            fraction = np.where(back, self.cycle_step, 1.0)
            step *= fraction[:, None]
            last_step = step
            U += step
            # the states move to the linearised prediction (within the defect tolerance for those that stop)
            nodes[:, 1:] = _moved(pred, sens, step)[:, :-1]
            stops = running & ~(go & ~last)
            # a fraction s of a Gauss-Newton step keeps s (2 - s) of the model's predicted decrease
            promised[stops] = (f - np.where(go, predicted * fraction * (2 - fraction), 0.0))[stops]
            running &= ~stops
            if not running.any():
                break
        U3 = U.reshape(-1, horizon, nu)
        X = reached(ocp, x0b, nodes, U3, steps, self.tol_final_defect)
        cost = (ocp.residuals(X, U3, refb, upb) ** 2).sum(-1)
        # a stop is confirmed only where the cost reached keeps the model's promise: above it, the model (states
        # with defects, or a Gauss-Newton model poor under large residuals) was optimistic, and so were the
        # predicted decreases the stopping tests extrapolated from
        slack = self.tol_promise_inexact if inexact else self.tol_gap
        broken = cost > promised + slack * np.abs(promised)
        # a handed-on plan goes to the next samples' steps where it ends below its start; any other stop must have
        # converged and kept its promise
        failed = ((running | broken) & ~handed_on) | ~np.isfinite(cost) | (cost > start_cost)
        if failed.any():  # rare: redo those problems by single shooting from the better of start and end
            rows = np.flatnonzero(failed)
            start = np.where(
                (cost[rows] < start_cost[rows])[:, None], U[rows], np.clip(U0, low, high).reshape(-1, n)[rows]
            )
            sub = super()._solve(
                ocp,
                x0b[rows],
                start.reshape(-1, horizon, nu),
                refb[rows],
                upb[rows],
                lo[rows].reshape(-1, horizon, nu),
                hi[rows].reshape(-1, horizon, nu),
                None,
                max_iter=self.max_iter if prior is None else min(self.max_iter, self.warm_max_iter),
            )
            U[rows], iterations[rows], cost[rows] = sub[0].reshape(-1, n), iterations[rows] + sub[1], sub[2]
            running[rows] = ~sub[3]
            X[rows] = ocp.rollout(x0b[rows], U[rows].reshape(-1, horizon, nu))
        return result(shape, project(U, lo, hi), iterations, cost, ~running, X)

    def _keeps(
        self, ocp: HorizonOCP, prior: Nd, before: Nd, U: Nd, states: Nd, width: Nd, at_limits: bool | None = None
    ) -> bool:
        """Whether a real-time step's plan stands: no step beyond rti_trust of the box's width (none is where every
        one is trusted) and neither the last plan nor this one at the joint limits' penalty (at_limits: already
        checked, compiled_step's answer)."""
        limits, trust = ocp.joint_limits, self.rti_trust
        if trust is not None and trust != np.inf and bool((np.abs(U - before) > trust * width).any()):
            return False
        if at_limits is not None:
            return not at_limits
        return limits is None or not limits.reached(np.concatenate((prior, states))).any()  # one call for both

    def warm_step(
        self, ocp: HorizonOCP, x0: Nd, U0: Nd, x_ref: Nd, u_prev: Nd, low: Nd, high: Nd, warm: object
    ) -> tuple[Nd, SolveInfo, LiftedWarm | NoWarm] | None:
        """The controller's warm sample as solve() returns it for one problem (x0 (nx,), U0 (H, nu), x_ref (H, nx),
        u_prev (nu,), bounds (nu,)), without its batch handling: one real-time step from the last plan's states,
        compiled or in numpy (_rti_steps). A plan that does not stand (_keeps) is solved on from that step as solve()
        would; None where solve() must run: no plan to start from, not a real-time iteration of one step."""
        if not (self.rti and self.rti_steps == 1 and isinstance(warm, LiftedWarm) and ocp.flow is not None):
            return None
        horizon, nx = ocp.horizon, ocp.nx
        if warm.states.shape != (1, horizon, nx):
            return None
        compiled = self._compiled(ocp)
        prior = warm.states
        nodes = np.empty((1, horizon, nx))
        nodes[0, 0], nodes[0, 1:] = x0, prior[0, 1:]
        before = np.minimum(np.maximum(U0, low), high).reshape(1, -1)
        lo, hi, width = self._warm_rows(U0.shape, low, high)
        data = (x_ref[None], u_prev[None], lo, hi)
        if compiled is None:
            U, states, cost = self._rti_steps(ocp, nodes, before, *data)
            at_limits = reached = None
        else:
            step = compiled_step(compiled, ocp, nodes, before, data, self.damping, prior, warm.reached)
            U, states, cost, at_limits, reached = step
        if self._keeps(ocp, prior, before, U, states, width, at_limits):
            info = SolveInfo(ONE_STEP, cost, UNCONVERGED, states)
            return U.reshape(U0.shape), info, LiftedWarm(states, reached)
        with np.errstate(divide="ignore", invalid="ignore"):  # as solve(): ratios of decreases not formed yet
            out = self._solve(
                ocp, x0[None], U0[None], x_ref[None], u_prev[None], low, high, prior, stepped=(U, states, cost)
            )
        U, iterations, cost, converged, states = out
        return U[0], SolveInfo(iterations, cost, converged, states), LiftedWarm(states)

    def _warm_rows(self, shape: tuple[int, ...], low: Nd, high: Nd) -> tuple[Nd, Nd, Nd]:
        """A warm sample's bounds as rows of one problem (1, H nu) and the box's width, read-only, kept from the last
        sample while the bounds (compared by value) and the horizon stay the same."""
        key = (shape, low.tobytes(), high.tobytes())
        kept = getattr(self, "_rows", None)  # not a field: no setting of the solver's
        if kept is None or kept[0] != key:
            lo, hi = _box_rows((1, *shape), low, high)
            kept = self._rows = (key, *(read_only(a) for a in (lo, hi, hi - lo)))
        return kept[1], kept[2], kept[3]

    def _rti_steps(
        self,
        ocp: HorizonOCP,
        nodes: np.ndarray,
        U: np.ndarray,
        refb: np.ndarray,
        upb: np.ndarray,
        lo: np.ndarray,
        hi: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Real-time iteration, the PINN counterpart of the classical controller's rti: rti_steps lifted Gauss-Newton
        steps (one by default) from the last plan's states, no convergence test and no further network call. Returns
        the inputs, the last step's linearised prediction of the states and its model cost (the problem counts as
        unconverged). Without a last plan, or with one at the joint limits, _solve solves fully."""
        compiled = self._compiled(ocp) if U.shape[0] == 1 else None
        for _ in range(self.rti_steps):
            if compiled is not None:
                U, states, cost, *_ = compiled_step(compiled, ocp, nodes, U, (refb, upb, lo, hi), self.damping)
                nodes[:, 1:] = states[:, :-1]
                continue
            pred, sens, _, _ = linearise(ocp, nodes, U)
            f, jtj, grad = ocp.gauss_newton_model(pred, sens, U, refb, upb)
            delta, _, predicted, _ = newton_step(jtj, grad, U, lo, hi, self.damping)
            step = np.clip(U + delta, lo, hi) - U
            U = U + step
            states = _moved(pred, sens, step)
            nodes[:, 1:] = states[:, :-1]
            cost = f - predicted
        return U, states, cost

    def prepare(self, ocp: HorizonOCP) -> None:
        """Build what a real-time iteration on this OCP will call (its compiled step) now, not in a warm sample."""
        if self.rti and ocp.flow is not None:
            self._compiled(ocp)

    def _compiles(self, ocp: HorizonOCP) -> bool:
        """Whether this OCP's real-time step runs compiled: asked for, and small enough to gain by it."""
        flops = step_flops(ocp.horizon, ocp.nx, ocp.nu, ocp.weights[np][0])
        return bool(self.compiled_step) and flops <= self.compiled_max_flops

    def _compiled(self, ocp: HorizonOCP) -> CompiledRti | None:
        """The compiled real-time step of this OCP's horizon, weights and damping (None: numpy's), decided and built
        on first use and kept with the OCP."""
        choice = (bool(self.compiled_step), float(self.compiled_max_flops), float(self.damping))
        last = getattr(self, "_last_compiled", None)  # the last one (not a field): cheaper than the weak lookup
        if last is not None and last[0] is ocp and last[1] == choice:
            return last[2]
        mine = STEP_OF.setdefault(ocp, {})
        if choice not in mine:
            mine[choice] = None
            if self._compiles(ocp):
                weights = ocp.weights[np]
                key = (ocp.horizon, ocp.nx, ocp.nu, self.damping, ocp.joint_limits)
                key += tuple(w if w is None else w.tobytes() for w in weights)
                if key not in COMPILED_STEPS:  # pure functions of their arguments: shared by every solver
                    jac_u = ocp.input_jacobian()
                    sizes = (ocp.horizon, ocp.nx, ocp.nu)
                    COMPILED_STEPS[key] = CompiledRti(*sizes, weights, jac_u, self.damping, ocp.joint_limits)
                mine[choice] = COMPILED_STEPS[key]
        self._last_compiled = (ocp, choice, mine[choice])
        return mine[choice]

    def _uses_warm(self, ocp: HorizonOCP) -> bool:
        """Whether a warm start can help here: the states warm start needs the numpy surrogate."""
        return ocp.flow is not None

    @staticmethod
    def _warm_shape(ocp: HorizonOCP) -> tuple[int, ...]:
        """Shape per problem of the warm array this solver takes: the last plan's states x_1..x_H."""
        return (ocp.horizon, ocp.nx)


ONE_STEP = read_only(np.ones(1, dtype=np.int64))  # a warm real-time sample's iterations, shared
UNCONVERGED = read_only(np.zeros(1, dtype=bool))  # ... and its convergence: a real-time step stops short by design
NODE_STEPS = 3  # Gauss-Newton steps of node_inputs: each one batched network call at the horizon's nodes


def node_inputs(
    ocp: HorizonOCP, nodes: np.ndarray, refb: np.ndarray, U: np.ndarray, lo: np.ndarray, hi: np.ndarray, damping: float
) -> np.ndarray:
    """A cold solve's inputs: at every node of the reference on its own, the input whose step lands nearest the next
    reference state (the OCP's state weight, its input weight as regularisation, within the box), by a few batched
    Gauss-Newton steps. With the lifted states at the reference this starts the horizon near its solution."""
    batch, horizon, nx = nodes.shape
    nu = ocp.nu
    w_q, w_r = ocp.weights[np][0], ocp.weights[np][1]
    u = U.reshape(batch, horizon, nu).copy()
    lo3, hi3 = lo.reshape(batch, horizon, nu), hi.reshape(batch, horizon, nu)
    for _ in range(NODE_STEPS):
        y, b = ocp.step_with_input_jacobian(nodes, u)
        wb = w_q @ b  # (B, H, nx, nu)
        r = ((y - refb) @ w_q.T)[..., None]  # (B, H, nx, 1)
        hess = wb.swapaxes(-1, -2) @ wb + w_r.T @ w_r
        hess += damping * np.eye(nu) * np.maximum(np.einsum("...ii->...", hess)[..., None, None] / nu, 1e-30)
        grad = wb.swapaxes(-1, -2) @ r + (w_r.T @ w_r @ u[..., None])
        u = np.clip(u - np.linalg.solve(hess, grad)[..., 0], lo3, hi3)
    return u.reshape(batch, horizon * nu)


def valid_trust(value: object) -> bool:
    """Whether a trust bound (rti_trust, system.control.rti_trust) is a number > 0 (inf included)."""
    return not isinstance(value, bool) and isinstance(value, int | float) and value > 0


def _box_rows(shape: tuple[int, ...], low: np.ndarray, high: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The bounds of every input of problems shaped (B, H, nu), as (B, H nu) rows."""
    rows = (-1, shape[-2] * shape[-1])
    return (np.zeros(shape) + low).reshape(rows), (np.zeros(shape) + high).reshape(rows)


def _moved(pred: np.ndarray, sens: np.ndarray, step: np.ndarray) -> np.ndarray:
    """The linearised prediction (B, H, nx) of the states after an input step: predictions plus sensitivities x step."""
    return pred + (sens @ step[..., None])[..., 0].reshape(pred.shape)
