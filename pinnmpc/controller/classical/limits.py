"""The soft joint limits of JointLimits (pinnmpc.controller.limits) in the classical NMPC: the penalty on the
symbolic states x_1..x_H and its Gauss-Newton Hessian, the same cost as the network OCP's residuals."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import casadi as ca

if TYPE_CHECKING:
    from pinnmpc.controller.classical.ocp import CasadiOCP


def limit_cost(ocp: CasadiOCP, xs: list) -> Any:
    """weight * (excess past limit - margin)^2 per limited side on x_1..x_H, the velocity towards that side times the
    lookahead counted in."""
    cost = 0
    for k in range(1, ocp.horizon + 1):
        for j, sign, edge in ocp.limit_sides:
            cost += ocp.joint_limits.weight * ca.fmax(0, limit_excess(ocp, xs[k], j, sign, edge)) ** 2
    return cost


def limit_excess(ocp: CasadiOCP, x: Any, j: int, sign: float, edge: float) -> Any:
    """How far joint j's checked position (JointLimits.ahead) lies past where one side's penalty starts."""
    excess = sign * (x[j] - edge)
    lookahead = ocp.joint_limits.lookahead
    return excess + lookahead * ca.fmax(0, sign * x[ocp.nx // 2 + j]) if lookahead else excess


def limit_hessian(ocp: CasadiOCP, xs: list) -> Any:
    """Gauss-Newton Hessian of the penalty (SX, nw x nw): 2 weight g g^T for each side whose checked position is past
    where its penalty starts, g the gradient of that position (the position's entry, and the lookahead on the
    velocity's while the joint moves towards that side), zero elsewhere (the residuals are piecewise linear)."""
    hess = ca.SX(ocp.nw, ocp.nw)
    lookahead, nq = ocp.joint_limits.lookahead, ocp.nx // 2
    for k in range(1, ocp.horizon + 1):
        for j, sign, edge in ocp.limit_sides:
            i = int(ocp.ix[k, j])
            active = 2.0 * ocp.joint_limits.weight * (limit_excess(ocp, xs[k], j, sign, edge) > 0)
            hess[i, i] += active
            if lookahead:
                iv, moving = int(ocp.ix[k, nq + j]), active * (sign * xs[k][nq + j] > 0)
                hess[i, iv] += lookahead * moving
                hess[iv, i] += lookahead * moving
                hess[iv, iv] += lookahead**2 * moving
    return hess
