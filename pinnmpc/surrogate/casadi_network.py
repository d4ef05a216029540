"""The trained flow map x(tau) = f(x0, u) as CasADi expressions built from the float64 weights, so that users can
put the surrogate into their own CasADi problems (Opti, nlpsol, code generation) with CasADi's exact derivatives.

The network is an MX graph (dense matrix products with the weights as constants: compact to serialise and to
generate C from); the frozen-arm prior, where the network has one, is the formula of ArmPrior.compiled as
an SX function called from that graph, with M^-1 kv by Cholesky and exp - I squared as such, so that it keeps
float64 agreement with torch's matrix_exp on a stiff 7-joint arm too.
"""

from __future__ import annotations

from collections.abc import Callable

import casadi as ca
import numpy as np
import torch

from pinnmpc.surrogate import mlp
from pinnmpc.surrogate.activations import Ops
from pinnmpc.surrogate.checkpoint import Surrogate
from pinnmpc.surrogate.matrix_exp import TAYLOR_DEGREE
from pinnmpc.surrogate.network import PINN
from pinnmpc.surrogate.prior import ArmPrior
from pinnmpc.surrogate.substeps import friction_substeps, midpoint_substeps

SOFTPLUS_THRESHOLD = 20.0  # torch's softplus returns its input above this, and so does the export


def _np(t: torch.Tensor) -> np.ndarray:
    """A float64 numpy copy of a module's tensor."""
    return t.detach().double().cpu().numpy().copy()


CASADI = Ops(
    "casadi", ca.tanh, ca.sin, ca.cos,
    sigmoid=lambda a: 0.5 + 0.5 * ca.tanh(0.5 * a),  # 1 / (1 + exp(-a)) overflows its derivative below -709
    softplus=lambda a: ca.if_else(a > SOFTPLUS_THRESHOLD, a, ca.log1p(ca.exp(a))),  # as torch computes it
    affine=lambda z, w, b: ca.mtimes(w, z) + b,  # column vectors, nn.Linear's (out, in) weight as a DM
    linear=lambda z, w: ca.mtimes(w, z),
    widen=lambda s: s,  # one direction per column: CasADi takes its own derivatives
)  # fmt: skip


def _network(model: PINN, t: ca.MX, x0: ca.MX, u: ca.MX) -> ca.MX:
    """The MLP output N (n_gates * n_head) at (t, x0, u): the same normalised input as PINN._inputs."""
    center, half = _np(model.in_center), _np(model.in_half)
    z = (ca.vertcat(t, x0, u) - center) / half
    if model.periodic:
        parts = [z[i] for i in range(z.shape[0])]
        for i in model.periodic:
            parts[1 + i] = ca.sin(x0[i])  # the sine replaces the normalised angle, as index_copy does
        z = ca.vertcat(*parts, *(ca.cos(x0[i]) for i in model.periodic))
        if len(model.sum_map):
            total = ca.mtimes(ca.DM(_np(model.sum_map)), x0)
            z = ca.vertcat(z, ca.sin(total), ca.cos(total))
    layers = [(ca.DM(_np(w)), _np(b)) for w, b in model.net.pairs()]
    return mlp.value(CASADI, layers, model.config["activation"], z)


def _expm1(x: ca.MX, squarings: int) -> ca.MX:
    """exp(x 2^s) - I: a Taylor series of exp(x) - I (Horner), then s squarings in the form (I + F)^2 - I = 2F + F^2,
    which keeps the near-identity part of the exponential (an arm's slow modes) to full relative precision where
    squaring exp itself would double its rounding error each time."""
    eye = ca.DM.eye(x.shape[0])
    out = eye
    for k in range(TAYLOR_DEGREE, 1, -1):
        out = eye + ca.mtimes(x, out) / k
    out = ca.mtimes(x, out)
    for _ in range(squarings):
        out = 2 * out + ca.mtimes(out, out)
    return out


def _relaxation(n: int, kv: np.ndarray) -> ca.Function:
    """M -> A = M^-1 kv by Cholesky (M is SPD; a symbolic QR solve loses digits on a stiff arm's M), in SX."""
    m = ca.SX.sym("m", n, n)
    chol = ca.chol(m)  # M = R^T R
    return ca.Function("relaxation", [m], [ca.solve(chol, ca.solve(chol.T, ca.diag(ca.DM(kv))))], {"cse": True})


def prior_function(prior: ArmPrior, tau: float) -> ca.Function:
    """x_p(tau) of the frozen-arm prior as a function (x0, u) -> x_p: ArmPrior.compiled's formula with M^-1 kv
    by Cholesky and E - I from _expm1, as matrix operations (MX), so that its Jacobian and C stay compact."""
    n, kv = prior.nq, prior.kv.numpy()
    h = tau / max(1, prior.steps)  # sub-steps with moving friction (ArmPrior.steps)
    s = prior.squarings(h)
    x, u = ca.MX.sym("x", 2 * n), ca.MX.sym("u", n)
    q0, v0 = x[:n], x[n:]
    frozen, relaxation = prior.arm.casadi_frozen_terms(settled=not prior.steps), _relaxation(n, kv)

    def held(q: ca.MX) -> tuple[ca.MX, ca.MX, ca.MX]:
        """v_ss, kv^-1 M (I - E) and E - I over h of the arm held at q."""
        m, c0 = frozen(q, u)
        e_minus_i = _expm1(-relaxation(m) * (h / 2**s), s)
        return c0 / ca.DM(kv), -ca.mtimes(ca.DM(np.diag(1 / kv)), ca.mtimes(m, e_minus_i)), e_minus_i

    if prior.midpoint:

        def terms(q: ca.MX) -> tuple[ca.MX, Callable]:
            """v_ss and the relaxation over h of the arm held at q."""
            vss, lag, e_minus_i = held(q)
            return vss, lambda d: (ca.mtimes(lag, d), d + ca.mtimes(e_minus_i, d))

        substeps = midpoint_substeps((q0, v0), terms, prior.moving_torque, ca.DM(kv), h, prior.steps)
        return ca.Function(f"{prior.arm.name}_frozen_prior", [x, u], [ca.vertcat(*substeps)])
    vss, lag, e_minus_i = held(q0)
    d = v0 - vss
    if prior.steps:
        relax = lambda d: (ca.mtimes(lag, d), d + ca.mtimes(e_minus_i, d))  # noqa: E731
        substeps = friction_substeps((q0, v0), vss, prior.moving_torque(q0), ca.DM(kv), h, relax, prior.steps)
        return ca.Function(f"{prior.arm.name}_frozen_prior", [x, u], [ca.vertcat(*substeps)])
    xp = ca.vertcat(q0 + vss * tau + ca.mtimes(lag, d), v0 + ca.mtimes(e_minus_i, d))  # vss + E d = v0 + (E - I) d
    return ca.Function(f"{prior.arm.name}_frozen_prior", [x, u], [xp])


def _gated(weights: np.ndarray, n: ca.MX, n_gates: int, n_head: int) -> ca.MX:
    """sum_k w_k N_k for N stacked gate-major (n_gates * n_head)."""
    out = 0
    for k in range(n_gates):
        out = out + float(weights[k]) * n[k * n_head : (k + 1) * n_head]
    return out


def flow_expression(surrogate: Surrogate, x0: ca.MX, u: ca.MX) -> ca.MX:
    """x(tau) as an MX expression in x0 (nx x 1) and u (nu x 1), as PINN.forward computes it at t = tau."""
    model, tau = surrogate.model, surrogate.tau
    t_tau = torch.full((1,), tau, dtype=torch.float64)
    if not model.exact_ic:
        return _np(model.out_center) + _np(model.out_scale) * _network(model, ca.MX(tau), x0, u)
    g = _np(model.gates(t_tau)[0])
    if model.second_order:  # q = q0 + v0 tau + s sum G_k N_k, v = v0 + s (sum g_k N_k + sum G_k dN_k/dt)
        t = ca.MX.sym("t")
        n = _network(model, t, x0, u)
        n, dn = ca.Function("net", [t, x0, u], [n, ca.jtimes(n, t, ca.MX(1))])(ca.MX(tau), x0, u)
        big_g = _np(model.gate_integrals(t_tau))
        scale, nq, heads = _np(model.head_scale), model.nq, (model.n_gates, model.n_head)
        q = x0[:nq] + tau * x0[nq:] + scale * _gated(big_g, n, *heads)
        v = x0[nq:] + scale * (_gated(g, n, *heads) + _gated(big_g, dn, *heads))
        return ca.vertcat(q, v)
    start = x0 if model.prior is None else prior_function(model.prior, tau)(x0, u[: model.prior_nu])  # its inputs
    n = _network(model, ca.MX(tau), x0, u)
    return start + _np(model.out_scale) * _gated(g, n, model.n_gates, model.n_head)


def casadi_flow(surrogate: Surrogate, name: str = "flow") -> tuple[ca.Function, ca.Function]:
    """f(x0, u) -> x1 and f_jac(x0, u) -> (x1, dx1/dx0, dx1/du) on column vectors, named name and name_jacobian."""
    x0, u = ca.MX.sym("x0", surrogate.nx), ca.MX.sym("u", surrogate.nu)
    x1 = flow_expression(surrogate, x0, u)
    f = ca.Function(name, [x0, u], [x1], ["x0", "u"], ["x1"])
    y = f(x0, u)  # the Jacobian of the function's call: the network graph once, not copied into the derivative
    outputs = [y, ca.jacobian(y, x0), ca.jacobian(y, u)]
    jac = ca.Function(f"{name}_jacobian", [x0, u], outputs, ["x0", "u"], ["x1", "dx1_dx0", "dx1_du"])
    return f, jac
