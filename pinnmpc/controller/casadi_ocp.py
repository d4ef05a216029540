"""The horizon OCP on the true model as a CasADi NLP: multiple shooting over RK4, stage-wise variables.

Variables w = (x_0, u_0, x_1, u_1, ..., x_{H-1}, u_{H-1}, x_H) and constraints g = (x_0 - x_meas,
x_1 - F(x_0, u_0) - d, ..., x_H - F(x_{H-1}, u_{H-1}) - d) are ordered stage by stage (fatrop's
structure detection needs that); the cost is the PINN controller's (pinnmpc.controller.ocp.HorizonOCP):
sum_{k=1..H} |x_k - xref_k|_Q^2 + sum_{k=0..H-1} |u_k|_R^2 + |u_k - u_{k-1}|_{R_rate}^2 with u_{-1} the
input applied last, plus the same soft joint-limit penalty on x_1..x_H (JointLimits). Parameters
p = (x_meas, xref_1..xref_H, u_prev, d).

With codegen, every function the solver evaluates (and F itself) is generated as C in one library
(pinnmpc.systems.compiled) and the solver is rebuilt on it: a solve is then the solver's own C/C++ loop
calling compiled code.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from pinnmpc.controller.ocp import JointLimits, psd_sqrt
from pinnmpc.plant.integrators import rk4_fixed
from pinnmpc.systems.compiled import compile_functions

SOLVERS = ("ipopt", "sqpmethod", "fatrop")  # nlpsol plugins this controller knows how to configure
OPT_LEVELS = ("-O0", "-O1", "-O2", "-O3", "-Os")  # C compiler optimisation levels for codegen
HESSIANS = ("gauss_newton", "exact")  # Hessian of the Lagrangian: the cost's only (constant) or with the dynamics'
RK4_STABLE = 2.0  # h * max|eig(df/dx)| kept below this (RK4's real stability bound is 2.785)
STIFFNESS_SAMPLES = 400  # states sampled to estimate the stiffest eigenvalue
SUCCESS = {  # return statuses that count as converged, per plugin
    "ipopt": {"Solve_Succeeded", "Solved_To_Acceptable_Level"},
    "sqpmethod": {"Solve_Succeeded"},
    "fatrop": {"Solve_Succeeded"},
}
QUIET = {  # options that silence each plugin
    "ipopt": {"ipopt": {"print_level": 0, "sb": "yes"}, "print_time": False},
    "sqpmethod": {
        "print_time": False,
        "print_header": False,
        "print_iteration": False,
        "print_status": False,
    },
    "fatrop": {"fatrop": {"print_level": 0}, "print_time": False},
}


def stable_rk4_steps(
    system: Any, tau: float, seed: int = 0, rhs: ca.Function | None = None, at_rest: bool = False
) -> int:
    """Fewest RK4 sub-steps per tau that keep h * max|eig(df/dx)| below RK4_STABLE on the state box (of rhs, by
    default the system's).

    Friction with a steep tanh makes the arms stiff near zero velocity, so half the samples there; with at_rest a
    quarter at exactly zero, where a smoothed sign(v) (tanh(v / width), any width) is steepest."""
    rhs = system.casadi_rhs() if rhs is None else rhs
    nx, nu = rhs.size1_in(0), rhs.size1_in(1)
    x, u = ca.SX.sym("x", nx), ca.SX.sym("u", nu)
    jac = ca.Function("rhs_jacobian", [x, u], [ca.jacobian(rhs(x, u), x)]).map(STIFFNESS_SAMPLES)
    rng = np.random.default_rng(seed)
    lo, hi = np.array(system.state_box.low), np.array(system.state_box.high)
    xs = rng.uniform(lo, hi, (STIFFNESS_SAMPLES, nx))
    xs[::2, nx // 2 :] *= 1e-3  # velocities near zero: the steepest friction slope
    if at_rest:
        xs[::4, nx // 2 :] = 0.0
    us = rng.uniform(system.input_box.low, system.input_box.high, (STIFFNESS_SAMPLES, nu))
    jacs = np.asarray(jac(xs.T, us.T)).reshape(nx, STIFFNESS_SAMPLES, nx).transpose(1, 0, 2)
    worst = float(np.abs(np.linalg.eigvals(jacs)).max())
    return max(1, math.ceil(tau * worst / RK4_STABLE))


def rk4_flow(rhs: ca.Function, tau: float, steps: int) -> tuple[ca.Function, ca.Function]:
    """F(x, u): the zero-order-hold flow over tau by `steps` RK4 steps, a loop (mapaccum) of one SX step, and
    F_sens(x, u) = (F, dF/dx, dF/du) by forward sensitivities carried through the same loop (one SX step with
    its own Jacobian, cheaper than AD through the loop)."""
    nx, nu = rhs.size1_in(0), rhs.size1_in(1)
    h = tau / steps
    x, u, s = ca.SX.sym("x", nx), ca.SX.sym("u", nu), ca.SX.sym("s", nx, nx + nu)
    nxt = rk4_fixed(rhs, x, u, h, 1)  # one step on symbols: the same RK4 as every other path
    step = ca.Function("rk4_step", [x, u], [nxt], {"cse": True})
    s_next = ca.jacobian(nxt, x) @ s + ca.horzcat(ca.SX.zeros(nx, nx), ca.jacobian(nxt, u))
    sens = ca.Function("rk4_sens", [x, u, s], [nxt, s_next], {"cse": True})
    xm, um = ca.MX.sym("x", nx), ca.MX.sym("u", nu)
    xs = step.mapaccum("rk4_loop", steps)(xm, ca.repmat(um, 1, steps))
    flow = ca.Function("F", [xm, um], [xs[:, -1]], ["x", "u"], ["xf"])
    s0 = ca.horzcat(ca.MX.eye(nx), ca.MX.zeros(nx, nu))
    xs, ss = sens.mapaccum("rk4_sens_loop", steps, [0, 2], [0, 1])(xm, ca.repmat(um, 1, steps), s0)
    last = ss[:, -(nx + nu) :]
    outs = [xs[:, -1], last[:, :nx], last[:, nx:]]
    return flow, ca.Function("F_sens", [xm, um], outs, ["x", "u"], ["xf", "A", "B"])


def _whole(value: Any) -> bool:
    """A count from a config or a caller: an int >= 1, never a float silently truncated or a bool."""
    return not isinstance(value, bool) and isinstance(value, (int, np.integer)) and value >= 1


def merged(base: dict, extra: dict) -> dict:
    """base updated by extra, nested dicts (a plugin's own options) merged key by key; copies."""
    out = {k: dict(v) if isinstance(v, dict) else v for k, v in base.items()}
    for k, v in extra.items():
        out[k] = merged(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def weight(matrix: Sequence, n: int, name: str) -> np.ndarray:
    """A PSD weight as a matrix (validated like the PINN controller's: a flat list is a diagonal)."""
    w = psd_sqrt(matrix, n, name).numpy()
    return w.T @ w


@dataclass
class Solution:
    """What one solve returned; the arrays are the solver's output buffers (copy what you keep)."""

    w: np.ndarray
    lam_x: np.ndarray
    lam_g: np.ndarray
    cost: float
    success: bool
    iterations: int
    status: str


class CasadiOCP:
    """The NLP, its layout and bounds; `solver` turns it into a callable nlpsol (compiled or not)."""

    def __init__(
        self,
        system: Any,
        horizon: int,
        Q: Sequence,
        R: Sequence,
        R_rate: Sequence | None,
        u_low: Sequence[float],
        u_high: Sequence[float],
        rk4_steps: int | None = None,
        joint_limits: JointLimits | Mapping | None = None,
        coulomb_width: float | None = None,
    ) -> None:
        if not _whole(horizon):
            raise ValueError(f"controller.horizon={horizon!r}; expected a whole number >= 1")
        rhs = system.casadi_rhs() if coulomb_width is None else system.casadi_rhs(coulomb_width)
        self.name = system.name
        self.horizon, self.nx, self.nu = int(horizon), rhs.size1_in(0), rhs.size1_in(1)
        self.tau = float(system.tau)
        if rk4_steps is None:
            rk4_steps = stable_rk4_steps(system, self.tau, rhs=rhs, at_rest=coulomb_width is not None)
        if not _whole(rk4_steps):
            raise ValueError(f"controller.rk4_steps={rk4_steps!r}; expected a whole number >= 1 or null (automatic)")
        self.rk4_steps = int(rk4_steps)
        self.low = np.array(u_low, dtype=np.float64)
        self.high = np.array(u_high, dtype=np.float64)
        if self.low.shape != (self.nu,) or self.high.shape != (self.nu,):
            raise ValueError(f"input bounds must have {self.nu} entries each, got {list(u_low)} and {list(u_high)}")
        if np.any(~(self.low <= self.high)):
            raise ValueError(f"input lower bound {self.low.tolist()} exceeds upper bound {self.high.tolist()}")
        self.Q, self.R = weight(Q, self.nx, "Q"), weight(R, self.nu, "R")
        self.R_rate = None if R_rate is None else weight(R_rate, self.nu, "R_rate")
        if self.R_rate is not None and not np.any(self.R_rate):
            self.R_rate = None
        self.joint_limits = JointLimits.from_config(joint_limits, self.nx // 2)
        self._limit_sides: list[tuple[int, float, float]] = []  # (joint, sign, where its penalty starts) per side
        if self.joint_limits is not None:
            for j, lo, hi in zip(self.joint_limits.joints, *self.joint_limits.inner):
                self._limit_sides += [(int(j), -1.0, lo)] if math.isfinite(lo) else []
                self._limit_sides += [(int(j), 1.0, hi)] if math.isfinite(hi) else []
        self.F, self.F_sens = rk4_flow(rhs, self.tau, self.rk4_steps)
        self._rollout_cost: ca.Function | None = None  # built on first use (see rollout_cost)
        self._layout()
        self._build()

    # -- layout ---------------------------------------------------------------------------------------------
    def _layout(self) -> None:
        """Index arrays of x_k (H+1, nx) and u_k (H, nu) in w, of the parts of p, and the bounds."""
        nx, nu, horizon = self.nx, self.nu, self.horizon
        stage = nx + nu
        self.ix = np.array([[k * stage + i for i in range(nx)] for k in range(horizon + 1)])
        self.iu = np.array([[k * stage + nx + i for i in range(nu)] for k in range(horizon)])
        self.nw, self.ng = (horizon + 1) * nx + horizon * nu, (horizon + 1) * nx
        self.np = nx + horizon * nx + nu + nx
        self.p_x0 = slice(0, nx)
        self.p_ref = slice(nx, nx + horizon * nx)
        self.p_uprev = slice(nx + horizon * nx, nx + horizon * nx + nu)
        self.p_d = slice(self.np - nx, self.np)
        self.lbw, self.ubw = np.full(self.nw, -np.inf), np.full(self.nw, np.inf)
        self.lbw[self.iu] = self.low
        self.ubw[self.iu] = self.high
        self.lbg, self.ubg = np.zeros(self.ng), np.zeros(self.ng)

    # -- the NLP --------------------------------------------------------------------------------------------
    def _split(self, w: Any, p: Any) -> tuple[list, list, Any, Any, Any, Any]:
        """States x_0..x_H, inputs u_0..u_{H-1} of w, and x_meas, xref (nx, H), u_prev, d of p (MX or SX)."""
        xs = [w[self.ix[k]] for k in range(self.horizon + 1)]
        us = [w[self.iu[k]] for k in range(self.horizon)]
        ref = ca.reshape(p[self.p_ref], self.nx, self.horizon)
        return xs, us, p[self.p_x0], ref, p[self.p_uprev], p[self.p_d]

    def _build(self) -> None:
        """Symbolic NLP (MX: every stage calls the same F) and the Gauss-Newton Hessian (SX, constant)."""
        w, p = ca.MX.sym("w", self.nw), ca.MX.sym("p", self.np)
        xs, us, x0, ref, u_prev, d = self._split(w, p)
        nxt = self.F.map(self.horizon)(ca.horzcat(*xs[:-1]), ca.horzcat(*us))
        g = [xs[0] - x0] + [xs[k + 1] - nxt[:, k] - d for k in range(self.horizon)]
        self.nlp = {"x": w, "p": p, "f": self._cost(xs, us, ref, u_prev), "g": ca.vertcat(*g)}
        # Gauss-Newton: the cost is quadratic in w, so its Hessian is exact and constant; only the dynamics'
        # curvature (lam_g^T d2g) is dropped.
        ws, ps = ca.SX.sym("x", self.nw), ca.SX.sym("p", self.np)
        lam_f, lam_g = ca.SX.sym("lam_f"), ca.SX.sym("lam_g", self.ng)
        xss, uss, _, refs, u_prevs, _ = self._split(ws, ps)
        hess = ca.sparsify(ca.evalf(ca.hessian(self._tracking_cost(xss, uss, refs, u_prevs), ws)[0]))
        hess = ca.triu(hess + self._limit_hessian(xss)) if self._limit_sides else ca.triu(hess)
        self.gauss_newton = ca.Function(
            "nlp_hess_l", [ws, ps, lam_f, lam_g], [lam_f * hess], ["x", "p", "lam_f", "lam_g"], ["triu_hess_gamma_x_x"]
        )

    def _with_sensitivities(self, w: Any, p: Any) -> tuple[Any, Any, Any]:
        """Cost, constraints and the constraints' Jacobian (MX) from F_sens: the compiled solvers' derivatives."""
        xs, us, x0, ref, u_prev, d = self._split(w, p)
        nx, nu = self.nx, self.nu
        nxt, a, b = self.F_sens.map(self.horizon)(ca.horzcat(*xs[:-1]), ca.horzcat(*us))
        g = ca.vertcat(xs[0] - x0, *[xs[k + 1] - nxt[:, k] - d for k in range(self.horizon)])
        rows = [ca.horzcat(ca.MX.eye(nx), ca.MX(nx, self.nw - nx))]  # d(x_0 - x_meas)/dw
        for k in range(self.horizon):  # d(x_{k+1} - F(x_k, u_k) - d)/dw: [-A_k, -B_k, I] on stage k's columns
            before, after = int(self.ix[k, 0]), self.nw - int(self.ix[k + 1, -1]) - 1
            block = [-a[:, k * nx : (k + 1) * nx], -b[:, k * nu : (k + 1) * nu], ca.MX.eye(nx)]
            rows.append(ca.horzcat(ca.MX(nx, before), *block, ca.MX(nx, after)))
        return self._cost(xs, us, ref, u_prev), g, ca.vertcat(*rows)

    def _cost(self, xs: list, us: list, ref: Any, u_prev: Any) -> Any:
        """The PINN controller's horizon cost on symbols (MX or SX), joint-limit penalty included."""
        cost = self._tracking_cost(xs, us, ref, u_prev)
        return cost + self._limit_cost(xs) if self._limit_sides else cost  # no limits: the very same expression

    def _limit_cost(self, xs: list) -> Any:
        """The soft joint limits of JointLimits on x_1..x_H: weight * (excess past limit - margin)^2 per side."""
        cost = 0
        for k in range(1, self.horizon + 1):
            for j, sign, edge in self._limit_sides:
                cost += self.joint_limits.weight * ca.fmax(0, sign * (xs[k][j] - edge)) ** 2
        return cost

    def _limit_hessian(self, xs: list) -> Any:
        """Gauss-Newton Hessian of the limit penalty (SX, nw x nw): 2 weight on the diagonal of each position past
        where its penalty starts, zero elsewhere (the penalty's residuals are piecewise linear)."""
        hess = ca.SX(self.nw, self.nw)
        for k in range(1, self.horizon + 1):
            for j, sign, edge in self._limit_sides:
                i = int(self.ix[k, j])
                hess[i, i] += 2.0 * self.joint_limits.weight * (sign * (xs[k][j] - edge) > 0)
        return hess

    def _tracking_cost(self, xs: list, us: list, ref: Any, u_prev: Any) -> Any:
        """The quadratic part of the cost: tracking, input and input-rate weights."""
        cost = 0
        for k in range(self.horizon):
            e = xs[k + 1] - ref[:, k]
            cost += ca.bilin(self.Q, e, e) + ca.bilin(self.R, us[k], us[k])
            if self.R_rate is not None:
                du = us[k] - (u_prev if k == 0 else us[k - 1])
                cost += ca.bilin(self.R_rate, du, du)
        return cost

    def rollout_cost(self, U: np.ndarray, p: np.ndarray) -> float:
        """The horizon cost of inputs U (H, nu) simulated through the model from p's state (a plan without defects):
        what an unconverged solve's inputs are worth against the previous plan's. Built on first use, uncompiled."""
        if self._rollout_cost is None:
            u, par = ca.MX.sym("u", self.horizon * self.nu), ca.MX.sym("p", self.np)
            us = [u[k * self.nu : (k + 1) * self.nu] for k in range(self.horizon)]
            xs, d = [par[self.p_x0]], par[self.p_d]
            for k in range(self.horizon):
                xs.append(self.F(xs[-1], us[k]) + d)
            ref = ca.reshape(par[self.p_ref], self.nx, self.horizon)
            self._rollout_cost = ca.Function("rollout_cost", [u, par], [self._cost(xs, us, ref, par[self.p_uprev])])
        return float(self._rollout_cost(np.asarray(U, dtype=np.float64).reshape(-1), p))

    # -- solvers --------------------------------------------------------------------------------------------
    def solver(
        self,
        plugin: str,
        options: dict[str, Any],
        hessian: str = "gauss_newton",
        codegen: bool = True,
        codegen_opt: str = "-O2",
    ) -> NlpSolver:
        """The nlpsol for this OCP: plugin (SOLVERS), its options (CasADi's names), compiled (at the C
        optimisation level codegen_opt) or not."""
        if codegen_opt not in OPT_LEVELS:
            raise ValueError(f"controller.codegen_opt={codegen_opt!r}; expected one of {list(OPT_LEVELS)}")
        if plugin not in SOLVERS:
            raise ValueError(f"solver={plugin!r}; expected one of {SOLVERS}")
        if not ca.has_nlpsol(plugin):
            raise ValueError(f"solver={plugin!r} is not available in this CasADi build ({ca.__version__})")
        if hessian not in HESSIANS:
            raise ValueError(f"hessian={hessian!r}; expected one of {HESSIANS}")
        gauss_newton = hessian == "gauss_newton"
        if gauss_newton and plugin == "fatrop" and not codegen:
            raise ValueError("fatrop takes no hess_lag option: hessian=gauss_newton needs codegen=true with fatrop")
        opts = merged(QUIET[plugin], options)
        if plugin == "fatrop":
            opts.setdefault("structure_detection", "auto")  # stage-wise variables and constraints
            opts.setdefault("equality", [True] * self.ng)
        if gauss_newton and plugin == "ipopt" and not self._limit_sides:  # the limits' Hessian is piecewise constant
            opts["ipopt"].setdefault("hessian_constant", "yes")
        if codegen:
            return self._compiled(plugin, opts, gauss_newton, codegen_opt)
        extra = {"hess_lag": self.gauss_newton} if gauss_newton else {}
        return NlpSolver(self, ca.nlpsol("ocp", plugin, self.nlp, {**opts, **extra}), self.F, SUCCESS[plugin])

    def _compiled(self, plugin: str, opts: dict, gauss_newton: bool, opt: str) -> NlpSolver:
        """The solver on a library of its functions compiled to C: CasADi loads every derivative the solver
        asks for (nlp_grad_f, nlp_jac_g, nlp_hess_l, ...) from the library that holds the oracle "nlp".
        The constraint Jacobians come from F_sens; with Gauss-Newton, nlp_hess_l is the constant cost Hessian."""
        nlp = self.nlp
        oracle = ca.Function("nlp", [nlp["x"], nlp["p"]], [nlp["f"], nlp["g"]], ["x", "p"], ["f", "g"])
        symbolic = ca.nlpsol("ocp", plugin, nlp, opts)  # names the functions the solver needs, and their signatures
        deps = []
        for f in (symbolic.get_function(n) for n in symbolic.get_function()):
            if f.name() in ("nlp_jac_g", "nlp_jac_fg"):
                f = self._like(f, gauss_newton=False)
            elif f.name() == "nlp_hess_l" and gauss_newton:
                f = self._like(f, gauss_newton=True)
            deps.append(f)
        x, u = self.F.mx_in()
        flow = ca.Function("flow", [x, u], [self.F(x, u)])
        tag = f"casadi_nmpc_{self.name}_{plugin}_{'gn' if gauss_newton else 'exact'}"
        lib = compile_functions(tag, [oracle, flow, *deps], opt=opt)
        return NlpSolver(self, ca.nlpsol("ocp", plugin, lib["nlp"], opts), lib["flow"], SUCCESS[plugin])

    def _like(self, template: ca.Function, gauss_newton: bool) -> ca.Function:
        """A replacement for one of the solver's derivative functions with its exact signature (the outputs
        differ per plugin), built on F_sens, projected onto the template's sparsity."""
        args = template.mx_in()
        w, p = args[0], args[1]
        f, g, jac = self._with_sensitivities(w, p)
        known = {"f": f, "g": g, "jac_g_x": jac, "jac_f_x": ca.jacobian(f, w), "grad_f_x": ca.gradient(f, w)}
        if gauss_newton:
            lam_f, lam_g = args[2], args[3]
            hess = self.gauss_newton(w, p, lam_f, lam_g)
            known["grad_gamma_x"] = lam_f * known["grad_f_x"] + ca.mtimes(jac.T, lam_g)
            known["triu_hess_gamma_x_x"], known["hess_gamma_x_x"] = hess, ca.triu2symm(hess)
        outs = []
        for i, name in enumerate(template.name_out()):
            if name not in known:
                raise ValueError(f"unexpected output {name!r} of the solver's {template.name()}; use codegen=false")
            outs.append(ca.project(known[name], template.sparsity_out(i)))
        return ca.Function(template.name(), args, outs, template.name_in(), template.name_out())


class NlpSolver:
    """An nlpsol evaluated through CasADi's buffer interface: numpy arrays in and out, no copies per call."""

    def __init__(self, ocp: CasadiOCP, solver: ca.Function, flow: ca.Function, success: set[str]) -> None:
        self.solver, self._success = solver, success
        self.w0, self.p = np.zeros(ocp.nw), np.zeros(ocp.np)
        self.lam_x0, self.lam_g0 = np.zeros(ocp.nw), np.zeros(ocp.ng)
        self._args = [self.w0, self.p, ocp.lbw.copy(), ocp.ubw.copy(), ocp.lbg.copy(), ocp.ubg.copy()]
        self._args += [self.lam_x0, self.lam_g0]
        self.w, self.cost, self.g = np.zeros(ocp.nw), np.zeros(1), np.zeros(ocp.ng)
        self.lam_x, self.lam_g, self.lam_p = np.zeros(ocp.nw), np.zeros(ocp.ng), np.zeros(ocp.np)
        self._res = [self.w, self.cost, self.g, self.lam_x, self.lam_g, self.lam_p]
        self._buf, self._trigger = solver.buffer()
        for i, a in enumerate(self._args):
            self._buf.set_arg(i, memoryview(a))
        for i, r in enumerate(self._res):
            self._buf.set_res(i, memoryview(r))
        # the flow F(x, u), for the offset-free estimator's one-step prediction
        self.flow_x, self.flow_u, self.flow_out = np.zeros(ocp.nx), np.zeros(ocp.nu), np.zeros(ocp.nx)
        self._fbuf, self._ftrigger = flow.buffer()
        self._fbuf.set_arg(0, memoryview(self.flow_x))
        self._fbuf.set_arg(1, memoryview(self.flow_u))
        self._fbuf.set_res(0, memoryview(self.flow_out))

    def __call__(self) -> Solution:
        """Solve from the current w0, lam_x0, lam_g0 and p (fill them in place first)."""
        self._trigger()
        stats = self._buf.stats()
        status = str(stats.get("return_status", "unknown"))
        return Solution(
            w=self.w,
            lam_x=self.lam_x,
            lam_g=self.lam_g,
            cost=float(self.cost[0]),
            success=bool(stats.get("success", False)) or status in self._success,
            iterations=int(stats.get("iter_count", 0)),
            status=status,
        )

    def flow(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """F(x, u) over one tau (undisturbed), a copy."""
        self.flow_x[:] = x
        self.flow_u[:] = u
        self._ftrigger()
        return self.flow_out.copy()
