"""The horizon OCP on the true model as a CasADi NLP: multiple shooting, variables and constraints stage by stage.

Stage k < H holds x_k, up_k (the input applied before it; only with an input-rate weight, so that the cost's Hessian
stays block diagonal), u_k and z_k (the transcription's own unknowns: none here; the collocation's stage
accelerations in pinnmpc.controller.classical.collocation); stage H holds x_H. The constraints come in the order a
structured QP solver (HPIPM) reads them, stage by stage: the dynamics x_{k+1} - F_k - d (and up_{k+1} - u_k), then
stage k's own: x_0 - x_meas (and up_0 - u_prev) at k = 0, and the transcription's residuals. The cost is the PINN
controller's (pinnmpc.controller.ocp.HorizonOCP): sum_{k=1..H} |x_k - xref_k|_Q^2 + sum_{k=0..H-1} |u_k|_R^2 +
|u_k - up_k|_{R_rate}^2, plus the same soft joint-limit penalty on x_1..x_H (JointLimits). Parameters
p = (x_meas, xref_1..xref_H, u_prev, d). This module's transcription: F_k = F(x_k, u_k), RK4 sub-steps over tau.

With codegen, every function the solver evaluates (and F itself) is generated as C in one library
(pinnmpc.systems.compiled) and the solver is rebuilt on it: a solve is then the solver's own C/C++ loop
calling compiled code.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from pinnmpc.controller.classical.limits import limit_cost, limit_hessian
from pinnmpc.controller.classical.nlpsol import QUIET, SUCCESS, NlpSolver, Solution
from pinnmpc.controller.classical.rk4 import rk4_flow, stable_rk4_steps
from pinnmpc.controller.limits import JointLimits
from pinnmpc.controller.ocp import psd_sqrt
from pinnmpc.systems.compiled import compile_functions

__all__ = ["CasadiOCP", "NlpSolver", "Solution", "Stages", "merged", "rk4_flow", "stable_rk4_steps", "weight"]

SOLVERS = ("ipopt", "sqpmethod", "fatrop")  # nlpsol plugins this controller knows how to configure
QPSOLS = ("qrqp", "hpipm", "osqp")  # sqpmethod QP solvers this controller configures (hpipm: with the stage structure)
OPT_LEVELS = ("-O0", "-O1", "-O2", "-O3", "-Os")  # C compiler optimisation levels for codegen
HESSIANS = ("gauss_newton", "exact")  # Hessian of the Lagrangian: the cost's only (constant) or with the dynamics'


def whole_number(value: Any) -> bool:
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
class Stages:
    """The NLP's variables and parameters split by stage (MX or SX); ups and zs are empty where the layout has none."""

    xs: list
    ups: list
    us: list
    zs: list
    x0: Any
    ref: Any
    u_prev: Any
    d: Any


Blocks = list[tuple[int, Any]]  # the nonzero blocks of one Jacobian block row: (first column in w, matrix)


class CasadiOCP:
    """The NLP, its layout and bounds; `solver` turns it into a callable nlpsol (compiled or not)."""

    transcription = "rk4"  # what predicts the next state (controller.transcription)

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
        if not whole_number(horizon):
            raise ValueError(f"controller.horizon={horizon!r}; expected a whole number >= 1")
        rhs = system.casadi_rhs() if coulomb_width is None else system.casadi_rhs(coulomb_width)
        self.name = system.name
        self.horizon, self.nx, self.nu = int(horizon), rhs.size1_in(0), rhs.size1_in(1)
        self.tau = float(system.tau)
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
        self.n_up = 0 if self.R_rate is None else self.nu  # the previous input as a stage variable: see the top
        self.nz = 0  # the transcription's unknowns per stage
        self.joint_limits = JointLimits.from_config(joint_limits, self.nx // 2)
        self.limit_sides: list[tuple[int, float, float]] = []  # (joint, sign, where its penalty starts) per side
        if self.joint_limits is not None:
            for j, lo, hi in zip(self.joint_limits.joints, *self.joint_limits.inner):
                self.limit_sides += [(int(j), -1.0, lo)] if math.isfinite(lo) else []
                self.limit_sides += [(int(j), 1.0, hi)] if math.isfinite(hi) else []
        self._prepare(system, rhs, coulomb_width, rk4_steps)
        self._rollout_cost: ca.Function | None = None  # built on first use (see rollout_cost)
        self._layout()
        self._build()

    def _prepare(self, system: Any, rhs: ca.Function, coulomb_width: float | None, rk4_steps: int | None) -> None:
        """The transcription's model: RK4 sub-steps (null: the fewest stable on the state box) and F, F_sens."""
        if rk4_steps is None:
            rk4_steps = stable_rk4_steps(system, self.tau, rhs=rhs, at_rest=coulomb_width is not None)
        if not whole_number(rk4_steps):
            raise ValueError(f"controller.rk4_steps={rk4_steps!r}; expected a whole number >= 1 or null (automatic)")
        self.rk4_steps = int(rk4_steps)
        self.F, self.F_sens = rk4_flow(rhs, self.tau, self.rk4_steps)

    @property
    def tag(self) -> str:
        """The transcription in a file name."""
        return "rk4"

    def describe(self) -> dict[str, Any]:
        """The transcription and its settings, for metrics.json."""
        return {"transcription": self.transcription, "rk4_steps": self.rk4_steps}

    # -- layout ---------------------------------------------------------------------------------------------
    def _layout(self) -> None:
        """Index arrays of x_k (H+1, nx), up_k, u_k, z_k (H, n) in w, of the constraint blocks in g (in
        _constraints' order), of the parts of p, and the bounds."""
        nx, nu, nup, nz, horizon = self.nx, self.nu, self.n_up, self.nz, self.horizon
        counter = itertools.count()

        def take(n: int) -> list[int]:
            return [next(counter) for _ in range(n)]

        ix, iup, iu, iz = [], [], [], []
        for _ in range(horizon):
            for rows, n in ((ix, nx), (iup, nup), (iu, nu), (iz, nz)):
                rows.append(take(n))
        ix.append(take(nx))
        self.nw = next(counter)
        as_array = lambda rows, n: np.array(rows, dtype=np.int64).reshape(len(rows), n)  # noqa: E731
        self.ix, self.iup, self.iu, self.iz = as_array(ix, nx), as_array(iup, nup), as_array(iu, nu), as_array(iz, nz)
        counter = itertools.count()
        gx, gup, gres, first = [], [], [], ([], [])
        for k in range(horizon):
            gx.append(take(nx))
            gup += [take(nup)] if k < horizon - 1 else []
            first = (take(nx), take(nup)) if k == 0 else first
            gres.append(take(nz))
        self.ng = next(counter)
        # blocks that move one stage forward when a solution is shifted (the last one repeated)
        self.w_blocks = [self.ix, self.iup, self.iu, self.iz]
        self.g_res = as_array(gres, nz)  # the transcription's residuals, per stage
        self.g_blocks = [as_array([first[0], *gx], nx), as_array([first[1], *gup], nup), self.g_res]
        self.np = nx + horizon * nx + nu + nx
        self.p_x0 = slice(0, nx)
        self.p_ref = slice(nx, nx + horizon * nx)
        self.p_uprev = slice(nx + horizon * nx, nx + horizon * nx + nu)
        self.p_d = slice(self.np - nx, self.np)
        self.lbw, self.ubw = np.full(self.nw, -np.inf), np.full(self.nw, np.inf)
        self.lbw[self.iu] = self.low
        self.ubw[self.iu] = self.high
        self.lbg, self.ubg = np.zeros(self.ng), np.zeros(self.ng)

    def qp_structure(self) -> dict[str, Any]:
        """The stage dimensions in HPIPM's terms (its qpsol options N, nx, nu, ng): states (x_k, up_k), inputs
        (u_k, z_k), and the constraints that are not dynamics."""
        horizon, states = self.horizon, self.nx + self.n_up
        return {
            "N": horizon,
            "nx": [states] * horizon + [self.nx],
            "nu": [self.nu + self.nz] * horizon + [0],
            "ng": [states + self.nz] + [self.nz] * (horizon - 1) + [0],
        }

    @staticmethod
    def shifted(values: np.ndarray, blocks: list[np.ndarray]) -> np.ndarray:
        """values with every stage block moved one stage forward, the last one kept (a warm start's shift)."""
        out = values.copy()
        for b in blocks:
            if b.size and len(b) > 1:
                out[b[:-1]] = values[b[1:]]
        return out

    def cold_start(self, w0: np.ndarray, x0: np.ndarray, U: np.ndarray, u_prev: np.ndarray) -> None:
        """A starting point without a previous solution, in place: every state at x0, the inputs U (H, nu)."""
        w0[self.ix] = x0
        w0[self.iu] = U
        w0[self.iup] = np.vstack([u_prev, U[:-1]]) if self.n_up else 0.0
        w0[self.iz] = 0.0

    def pin_start(self, w0: np.ndarray, x0: np.ndarray, u_prev: np.ndarray) -> None:
        """The first stage's known values into a shifted starting point: the initial constraints hold at the start."""
        w0[self.ix[0]] = x0
        if self.n_up:
            w0[self.iup[0]] = u_prev

    # -- the NLP --------------------------------------------------------------------------------------------
    def _split(self, w: Any, p: Any) -> Stages:
        """w and p by stage (MX or SX)."""
        horizon = self.horizon
        return Stages(
            xs=[w[self.ix[k]] for k in range(horizon + 1)],
            ups=[w[self.iup[k]] for k in range(horizon)] if self.n_up else [],
            us=[w[self.iu[k]] for k in range(horizon)],
            zs=[w[self.iz[k]] for k in range(horizon)] if self.nz else [],
            x0=p[self.p_x0],
            ref=ca.reshape(p[self.p_ref], self.nx, horizon),
            u_prev=p[self.p_uprev],
            d=p[self.p_d],
        )

    def _model(self, s: Stages, jac: bool) -> tuple[list, list, list[Blocks], list[Blocks]]:
        """Per stage: the predicted next state, the residuals (none here) and, with jac, their derivatives' blocks
        (F_sens: cheaper than AD through the RK4 loop)."""
        horizon, nx, nu = self.horizon, self.nx, self.nu
        X, U = ca.horzcat(*s.xs[:-1]), ca.horzcat(*s.us)
        if not jac:
            nxt = self.F.map(horizon)(X, U)
            return [nxt[:, k] for k in range(horizon)], [], [], []
        nxt, a, b = self.F_sens.map(horizon)(X, U)
        blocks = [
            [(int(self.ix[k, 0]), a[:, k * nx : (k + 1) * nx]), (int(self.iu[k, 0]), b[:, k * nu : (k + 1) * nu])]
            for k in range(horizon)
        ]
        return [nxt[:, k] for k in range(horizon)], [], blocks, []

    def _constraints(self, s: Stages, nxt: list, res: list) -> Any:
        """g in the order of the layout: per stage the dynamics, then x_0 - x_meas (k = 0) and the residuals."""
        rows = []
        for k in range(self.horizon):
            rows.append(s.xs[k + 1] - nxt[k] - s.d)
            if self.n_up and k < self.horizon - 1:
                rows.append(s.ups[k + 1] - s.us[k])
            if k == 0:
                rows += [s.xs[0] - s.x0] + ([s.ups[0] - s.u_prev] if self.n_up else [])
            if self.nz:
                rows.append(res[k])
        return ca.vertcat(*rows)

    def _jacobian(self, dnxt: list[Blocks], dres: list[Blocks]) -> Any:
        """dg/dw (MX) block row by block row, in _constraints' order."""
        nx, nu, horizon = self.nx, self.nu, self.horizon
        eye_x, eye_u = ca.MX.eye(nx), ca.MX.eye(nu)
        rows = []
        for k in range(horizon):
            rows.append(self._row(nx, [(int(self.ix[k + 1, 0]), eye_x)] + [(c, -b) for c, b in dnxt[k]]))
            if self.n_up and k < horizon - 1:
                rows.append(self._row(nu, [(int(self.iu[k, 0]), -eye_u), (int(self.iup[k + 1, 0]), eye_u)]))
            if k == 0:
                rows.append(self._row(nx, [(int(self.ix[0, 0]), eye_x)]))
                rows += [self._row(nu, [(int(self.iup[0, 0]), eye_u)])] if self.n_up else []
            if self.nz:
                rows.append(self._row(self.nz, dres[k]))
        return ca.vertcat(*rows)

    def _row(self, n: int, blocks: Blocks) -> Any:
        """One block row of n rows: the blocks at their columns, structural zeros between."""
        parts, col = [], 0
        for start, block in sorted(blocks, key=lambda b: b[0]):
            parts += [ca.MX(n, start - col)] if start > col else []
            parts.append(ca.MX(block))
            col = start + block.shape[1]
        parts += [ca.MX(n, self.nw - col)] if col < self.nw else []
        return ca.horzcat(*parts)

    def _build(self) -> None:
        """Symbolic NLP (MX: every stage calls the same functions) and the Gauss-Newton Hessian (SX, constant)."""
        w, p = ca.MX.sym("w", self.nw), ca.MX.sym("p", self.np)
        s = self._split(w, p)
        nxt, res, _, _ = self._model(s, jac=False)
        self.nlp = {"x": w, "p": p, "f": self._cost(s.xs, s.us, s.ref, s.ups), "g": self._constraints(s, nxt, res)}
        # Gauss-Newton: the cost is quadratic in w, so its Hessian is exact and constant; only the constraints'
        # curvature (lam_g^T d2g) is dropped.
        ws, ps = ca.SX.sym("x", self.nw), ca.SX.sym("p", self.np)
        lam_f, lam_g = ca.SX.sym("lam_f"), ca.SX.sym("lam_g", self.ng)
        ss = self._split(ws, ps)
        hess = ca.sparsify(ca.evalf(ca.hessian(self._tracking_cost(ss.xs, ss.us, ss.ref, ss.ups), ws)[0]))
        hess = ca.triu(hess + limit_hessian(self, ss.xs)) if self.limit_sides else ca.triu(hess)
        self.gauss_newton = ca.Function(
            "nlp_hess_l", [ws, ps, lam_f, lam_g], [lam_f * hess], ["x", "p", "lam_f", "lam_g"], ["triu_hess_gamma_x_x"]
        )

    def _with_sensitivities(self, w: Any, p: Any) -> tuple[Any, Any, Any]:
        """Cost, constraints and the constraints' Jacobian (MX) from the model's own derivatives: the compiled
        solvers' derivatives."""
        s = self._split(w, p)
        nxt, res, dnxt, dres = self._model(s, jac=True)
        return self._cost(s.xs, s.us, s.ref, s.ups), self._constraints(s, nxt, res), self._jacobian(dnxt, dres)

    def _cost(self, xs: list, us: list, ref: Any, prev: list) -> Any:
        """The PINN controller's horizon cost on symbols (MX or SX), joint-limit penalty included; prev[k]: the input
        before u_k (for the rate weight)."""
        cost = self._tracking_cost(xs, us, ref, prev)
        return cost + limit_cost(self, xs) if self.limit_sides else cost  # no limits: the very same expression

    def _tracking_cost(self, xs: list, us: list, ref: Any, prev: list) -> Any:
        """The quadratic part of the cost: tracking, input and input-rate weights."""
        cost = 0
        for k in range(self.horizon):
            e = xs[k + 1] - ref[:, k]
            cost += ca.bilin(self.Q, e, e) + ca.bilin(self.R, us[k], us[k])
            if self.R_rate is not None:
                du = us[k] - prev[k]
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
            ref, prev = ca.reshape(par[self.p_ref], self.nx, self.horizon), [par[self.p_uprev], *us[:-1]]
            self._rollout_cost = ca.Function("rollout_cost", [u, par], [self._cost(xs, us, ref, prev)])
        return float(self._rollout_cost(np.asarray(U, dtype=np.float64).reshape(-1), p))

    # -- solvers --------------------------------------------------------------------------------------------
    def solver(
        self,
        plugin: str,
        options: dict[str, Any],
        hessian: str = "gauss_newton",
        codegen: bool = True,
        codegen_opt: str = "-O2",
        extra: Sequence[ca.Function] = (),
    ) -> NlpSolver:
        """The nlpsol for this OCP: plugin (SOLVERS), its options (CasADi's names), compiled (at the C
        optimisation level codegen_opt) or not; extra functions go into the same library (NlpSolver.functions):
        code they share with the solver's is generated once."""
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
        if plugin == "sqpmethod":
            qpsol = opts.setdefault("qpsol", "qrqp")
            if qpsol not in QPSOLS or not ca.has_conic(qpsol):
                have = [q for q in QPSOLS if ca.has_conic(q)]
                raise ValueError(f"controller.qpsol={qpsol!r}; expected one of {have} (available in this CasADi build)")
            if qpsol == "hpipm":  # the Riccati recursion needs the stages: HPIPM's own detection misreads this layout
                opts["qpsol_options"] = {**self.qp_structure(), **opts.get("qpsol_options", {})}
        if plugin == "fatrop":
            opts.setdefault("structure_detection", "auto")  # stage-wise variables and constraints
            opts.setdefault("equality", [True] * self.ng)
        if gauss_newton and plugin == "ipopt" and not self.limit_sides:  # the limits' Hessian is piecewise constant
            opts["ipopt"].setdefault("hessian_constant", "yes")
        if codegen:
            return self._compiled(plugin, opts, gauss_newton, codegen_opt, list(extra))
        hess = {"hess_lag": self.gauss_newton} if gauss_newton else {}
        solver = ca.nlpsol("ocp", plugin, self.nlp, {**opts, **hess})
        return NlpSolver(self, solver, self.flow_function(), SUCCESS[plugin], {f.name(): f for f in extra})

    def _compiled(self, plugin: str, opts: dict, gauss_newton: bool, opt: str, extra: list) -> NlpSolver:
        """The solver on a library of its functions compiled to C: CasADi loads every derivative the solver
        asks for (nlp_grad_f, nlp_jac_g, nlp_hess_l, ...) from the library that holds the oracle "nlp".
        The constraint Jacobians come from the model's own derivatives (_model); with Gauss-Newton, nlp_hess_l is
        the constant cost Hessian."""
        nlp = self.nlp
        oracle = ca.Function("nlp", [nlp["x"], nlp["p"]], [nlp["f"], nlp["g"]], ["x", "p"], ["f", "g"])
        symbolic = ca.nlpsol("ocp", plugin, nlp, opts)  # names the functions the solver needs, and their signatures
        deps = []
        for f in (symbolic.get_function(n) for n in symbolic.get_function()):
            if f.name() in ("nlp_jac_g", "nlp_jac_fg", "nlp_grad"):  # not AD through the model: its own blocks
                f = self._like(f, gauss_newton=False)
            elif f.name() == "nlp_hess_l" and gauss_newton:
                f = self._like(f, gauss_newton=True)
            deps.append(f)
        tag = f"casadi_nmpc_{self.name}_{self.tag}_{plugin}_{'gn' if gauss_newton else 'exact'}"
        lib = compile_functions(tag, [oracle, self.flow_function(), *deps, *extra], opt=opt)
        solver = ca.nlpsol("ocp", plugin, lib["nlp"], opts)
        return NlpSolver(self, solver, lib["flow"], SUCCESS[plugin], {f.name(): lib[f.name()] for f in extra})

    def flow_function(self) -> ca.Function:
        """flow(x, u, z): F(x, u), from a guess z of the transcription's unknowns (none here)."""
        x, u, z = ca.MX.sym("x", self.nx), ca.MX.sym("u", self.nu), ca.MX.sym("z", self.nz)
        return ca.Function("flow", [x, u, z], [self.F(x, u)], ["x", "u", "z"], ["xf"])

    def _like(self, template: ca.Function, gauss_newton: bool) -> ca.Function:
        """A replacement for one of the solver's derivative functions with its exact signature (the outputs
        differ per plugin), built on the model's derivatives, projected onto the template's sparsity."""
        args = template.mx_in()
        named = dict(zip(template.name_in(), args))
        w, p = named["x"], named["p"]
        f, g, jac = self._with_sensitivities(w, p)
        known = {"f": f, "g": g, "jac_g_x": jac, "jac_f_x": ca.jacobian(f, w), "grad_f_x": ca.gradient(f, w)}
        if "lam_g" in named:  # the Lagrangian f lam_f + g^T lam_g
            lam_f, lam_g = named["lam_f"], named["lam_g"]
            known["grad_gamma_x"] = lam_f * known["grad_f_x"] + ca.mtimes(jac.T, lam_g)
            horizon = self.horizon  # g's part in p is affine (-x_meas, -u_prev, -d): g at w = 0 without the model
            s, zero = self._split(ca.MX(self.nw, 1), p), [ca.MX(self.nx, 1)] * horizon
            g_p = self._constraints(s, zero, [ca.MX(self.nz, 1)] * horizon)
            known["grad_gamma_p"] = ca.gradient(lam_f * f + ca.dot(lam_g, g_p), p)
        if gauss_newton:
            hess = self.gauss_newton(w, p, named["lam_f"], named["lam_g"])
            known["triu_hess_gamma_x_x"], known["hess_gamma_x_x"] = hess, ca.triu2symm(hess)
        outs = []
        for i, name in enumerate(template.name_out()):
            if name not in known:
                raise ValueError(f"unexpected output {name!r} of the solver's {template.name()}; use codegen=false")
            outs.append(ca.project(known[name], template.sparsity_out(i)))
        return ca.Function(template.name(), args, outs, template.name_in(), template.name_out())
