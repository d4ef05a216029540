"""Real-time iteration of the classical NMPC: one Gauss-Newton SQP step per sample, on a condensed QP.

The collocation's stage accelerations z_k carry no cost and enter only the residuals R_k (with R_z invertible) and
the end state, so they are eliminated stage by stage in the generated C, dz_k = -R_z^-1 (R_k + R_x dx_k + R_u du_k):
what is left is the QP of multiple shooting in (x_k, up_k, u_k) with the dynamics' Jacobian condensed, whose step
is the full QP's. A structured QP solver (HPIPM's Riccati recursion) then sees nu inputs per stage instead of
nu + nz, and none of the residual equalities an interior point can only approach. With RK4 nothing is eliminated:
the step is sqpmethod's single step without the second Jacobian evaluation (its convergence test after the step,
which a real-time iteration does not use).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import casadi as ca
import numpy as np

from pinnmpc.controller.classical.nlpsol import Solution
from pinnmpc.controller.classical.ocp import CasadiOCP

RTI_STATUS = "RTI_step"  # a step whose QP was solved (a real-time iteration is unconverged by design)
QP_TOLERANCE = 1e-6  # a QP step that violates its linearised constraints or bounds by more failed


def kept_columns(ocp: CasadiOCP) -> np.ndarray:
    """The variables of the condensed QP: all but the transcription's unknowns z_k, in w's order."""
    return np.setdiff1d(np.arange(ocp.nw), ocp.iz.ravel())


def kept_rows(ocp: CasadiOCP) -> np.ndarray:
    """The constraints of the condensed QP: all but the residuals, in g's order."""
    return np.setdiff1d(np.arange(ocp.ng), ocp.g_res.ravel())


def rti_structure(ocp: CasadiOCP) -> dict[str, Any]:
    """The condensed QP's stages in HPIPM's terms: states (x_k, up_k), inputs u_k, x_0 - x_meas (and up_0 - u_prev)
    the only constraints that are not dynamics."""
    horizon, states = ocp.horizon, ocp.nx + ocp.n_up
    return {
        "N": horizon,
        "nx": [states] * horizon + [ocp.nx],
        "nu": [ocp.nu] * horizon + [0],
        "ng": [states] + [0] * horizon,
    }


def rti_function(ocp: CasadiOCP) -> ca.Function:
    """(w, p) -> the condensed QP at w: the cost f, its gradient and (Gauss-Newton) Hessian on the kept variables, the
    kept constraints and their Jacobian, and per stage S_k = R_z^-1 [R_x R_u R_k] (nz x (nx + nu + 1), side by side)
    to recover dz_k = -S_k (dx_k, du_k, 1)."""
    w, p = ocp.nlp["x"], ocp.nlp["p"]
    s = ocp._split(w, p)
    nxt, res, dnxt, dres = ocp._model(s, jac=True)
    nx, nu, nz = ocp.nx, ocp.nu, ocp.nz
    eye_x, eye_u = ca.MX.eye(nx), ca.MX.eye(nu)
    rows, values, maps = [], [], []
    for k in range(ocp.horizon):
        ix, iu, iz = int(ocp.ix[k, 0]), int(ocp.iu[k, 0]), int(ocp.iz[k, 0]) if nz else -1
        blocks = dict(dnxt[k])
        a, b = blocks.get(ix, ca.MX(nx, nx)), blocks.get(iu, ca.MX(nx, nu))
        defect = s.xs[k + 1] - nxt[k] - s.d
        if nz:
            r = dict(dres[k])
            smap = ca.solve(r[iz], ca.horzcat(r[ix], r[iu], res[k]), "qr")
            a, b = a - blocks[iz] @ smap[:, :nx], b - blocks[iz] @ smap[:, nx : nx + nu]
            defect += blocks[iz] @ smap[:, -1]
            maps.append(smap)
        rows.append(ocp._row(nx, [(int(ocp.ix[k + 1, 0]), eye_x), (ix, -a), (iu, -b)]))
        values.append(defect)
        if ocp.n_up and k < ocp.horizon - 1:
            rows.append(ocp._row(nu, [(iu, -eye_u), (int(ocp.iup[k + 1, 0]), eye_u)]))
            values.append(s.ups[k + 1] - s.us[k])
        if k == 0:
            rows.append(ocp._row(nx, [(ix, eye_x)]))
            values.append(s.xs[0] - s.x0)
            if ocp.n_up:
                rows.append(ocp._row(nu, [(int(ocp.iup[0, 0]), eye_u)]))
                values.append(s.ups[0] - s.u_prev)
    keep = kept_columns(ocp).tolist()
    f = ocp._cost(s.xs, s.us, s.ref, s.ups)
    hess = ca.triu2symm(ocp.gauss_newton(w, p, 1.0, ca.MX(ocp.ng, 1)))[keep, keep]
    outs = [f, ca.gradient(f, w)[keep], hess, ca.vertcat(*values), ca.vertcat(*rows)[:, keep]]
    outs.append(ca.horzcat(*maps) if nz else ca.MX(0, 0))
    return ca.Function("rti_qp", [w, p], outs, ["x", "p"], ["f", "grad", "hess", "g", "jac", "smap"])


class RtiSolver:
    """One condensed Gauss-Newton step per call, with NlpSolver's buffers (w0, p, lam_x0, lam_g0) and Solution."""

    def __init__(self, ocp: CasadiOCP, step: ca.Function, flow: Callable) -> None:
        self.ocp, self.flow = ocp, flow
        self.keep, self.rows = kept_columns(ocp), kept_rows(ocp)
        self.w0, self.p = np.zeros(ocp.nw), np.zeros(ocp.np)
        self.lam_x0, self.lam_g0 = np.zeros(ocp.nw), np.zeros(ocp.ng)  # kept for the interface: GN needs none
        self._bounds = (ocp.lbw[self.keep].copy(), ocp.ubw[self.keep].copy())
        self._out = [np.zeros(step.nnz_out(i)) for i in range(step.n_out())]  # dy, cost, lam_a, lam_y, smap, error
        self._buf, self._run = step.buffer()
        for i, a in enumerate((self.w0, self.p, *self._bounds)):
            self._buf.set_arg(i, memoryview(a))
        for i, r in enumerate(self._out):
            self._buf.set_res(i, memoryview(r))
        self.w, self.lam_x, self.lam_g = np.zeros(ocp.nw), np.zeros(ocp.nw), np.zeros(ocp.ng)
        position = {int(c): i for i, c in enumerate(self.keep)}  # where x_k and u_k sit among the kept variables
        self._dx = np.array([[position[int(c)] for c in row] for row in ocp.ix[:-1]], dtype=np.int64)
        self._du = np.array([[position[int(c)] for c in row] for row in ocp.iu]).reshape(ocp.horizon, ocp.nu)

    def __call__(self) -> Solution:
        """One step from the current w0 and p (fill them in place first)."""
        ocp, keep = self.ocp, self.keep
        self._run()
        dy, cost, lam_a, lam_y, smap, error = self._out
        self.w[:] = self.w0
        self.w[keep] += dy
        if ocp.nz:  # dz_k = -S_k (dx_k, du_k, 1), S_k^T read row by row from the column-major buffer
            nx, nu = ocp.nx, ocp.nu
            s = smap.reshape(ocp.horizon, nx + nu + 1, ocp.nz)
            dx, du = dy[self._dx], dy[self._du]
            dz = np.einsum("kci,kc->ki", s[:, :nx], dx) + np.einsum("kci,kc->ki", s[:, nx : nx + nu], du) + s[:, -1]
            self.w[ocp.iz] -= dz
        self.lam_g[:] = 0.0
        self.lam_g[self.rows] = lam_a
        self.lam_x[:] = 0.0
        self.lam_x[keep] = lam_y
        status = RTI_STATUS if error[0] <= QP_TOLERANCE else "QP_failed"  # not <=: NaN fails too
        return Solution(self.w, self.lam_x, self.lam_g, float(cost[0]), success=False, iterations=1, status=status)


def rti_solver(
    ocp: CasadiOCP, qpsol: str, qp_options: dict[str, Any], qp_data: ca.Function, flow: Callable
) -> RtiSolver:
    """The condensed real-time iteration of this OCP on qp_data (rti_function's, compiled or not) with QP solver qpsol
    (its options; HPIPM gets the stages): QP data and QP solver in one function (CasADi's buffer interface misfeeds
    HPIPM called alone)."""
    opts = {**rti_structure(ocp), **qp_options} if qpsol == "hpipm" else dict(qp_options)
    sparsity = {"h": qp_data.sparsity_out("hess"), "a": qp_data.sparsity_out("jac")}
    conic = ca.conic("rti_qp_solver", qpsol, sparsity, opts)
    keep = kept_columns(ocp).tolist()
    w, p = ca.MX.sym("w", ocp.nw), ca.MX.sym("p", ocp.np)
    low, high = ca.MX.sym("lbx", len(keep)), ca.MX.sym("ubx", len(keep))
    f, grad, hess, g, jac, smap = qp_data(w, p)
    qp = conic(h=hess, g=grad, a=jac, lba=-g, uba=-g, lbx=low - w[keep], ubx=high - w[keep])
    outside = ca.fmax(0, ca.fmax(low - w[keep] - qp["x"], qp["x"] - high + w[keep]))  # 0 within the bounds
    error = ca.norm_inf(ca.vertcat(jac @ qp["x"] + g, outside))
    outs = [qp["x"], f + qp["cost"], qp["lam_a"], qp["lam_x"], smap, error]
    return RtiSolver(ocp, ca.Function("rti_step", [w, p, low, high], outs), flow)
