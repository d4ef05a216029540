"""The sub-step formulas of the frozen-arm priors (pinnmpc.surrogate.prior), written once for every array namespace:
torch in training, CasADi SX in the controller's C and MX in the export. Each sub-step is the exact flow of the arm
held with its torques fixed; what changes between the kinds is where the arm is held and at which velocity its
moving torques are taken."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from torch import Tensor


def friction_substeps(
    x0: tuple[Any, Any],
    vss: Any,
    friction: Callable[[Any], Any],
    kv: Any,
    h: Any,
    relax: Callable,
    steps: int,
    spans: list[tuple[Any, Callable]] | None = None,
) -> tuple[Any, Any]:
    """(q, v) after `steps` sub-steps of h of the arm frozen at q0 with its dry friction at the moving velocity: per
    sub-step the friction is held at the mean of the start velocity and a predicted end velocity (exponential Heun),
    the linear rest solved exactly; relax(d) -> (kv^-1 M (I - E(h)) d, E(h) d); any array namespace. x0 = (q0, v0),
    vss = c0 / kv of the drive without the friction. spans: per sub-step the (length, relax) it advances by, its
    torques still predicted over h (ArmPrior._solve_moving: x_p(t) for t anywhere on the grid of h)."""
    for k in range(steps):
        predicted = held_flow(x0, vss, friction(x0[1]), kv, h, relax)[1]
        x0 = held_flow(x0, vss, friction(0.5 * (x0[1] + predicted)), kv, *(spans[k] if spans else (h, relax)))
    return x0


def held_flow(x0: tuple[Any, Any], vss: Any, torque: Any, kv: Any, length: Any, relax: Callable) -> tuple[Any, Any]:
    """(q, v) after `length` of M dv/dt = c0 - torque - kv v, dq/dt = v from x0 with the torque held: the exact flow
    every sub-step is; relax(d) -> (kv^-1 M (I - E(length)) d, E(length) d)."""
    q, v = x0
    ss = vss - torque / kv
    lag_d, e_d = relax(v - ss)
    return q + ss * length + lag_d, ss + e_d


def predicted_mid(x0: tuple[Any, Any], held: tuple[Any, Callable], h: Any) -> Any:
    """The configuration half way through a sub-step of h from x0, predicted by the arm held as `held` = (v_ss,
    relax over h) says, without its moving torques: where midpoint_substeps takes M, gravity and the Coriolis
    torques for it (the moving torques would move it by nothing the targets see: docs/training-findings.md)."""
    vss, relax = held
    return x0[0] + 0.5 * (vss * h + relax(x0[1] - vss)[0])


def midpoint_step(
    x0: tuple[Any, Any],
    held: tuple[Any, Callable],
    torque: Callable[[Any], Any],
    kv: Any,
    h: Any,
    lagged: Any,
    span: tuple[Any, Callable] | None = None,
) -> tuple[tuple[Any, Any], Any]:
    """One sub-step of h of the arm held as held = (v_ss, relax over h), its moving torques (torque: w -> them)
    held at the mean of the start velocity and an end velocity predicted with the torques `lagged` (those the
    sub-step before held, already at hand: as close as the start's own, docs/training-findings.md); (q, v) and the
    torques it held. span: the (length, relax) it advances by, its torques still predicted over h (_solve_midpoint)."""
    vss, relax = held
    mean = torque(0.5 * (x0[1] + held_flow(x0, vss, lagged, kv, h, relax)[1]))
    return held_flow(x0, vss, mean, kv, *(span or (h, relax))), mean


def midpoint_substeps(
    x0: tuple[Any, Any],
    terms: Callable[[Any], tuple[Any, Callable]],
    torque: Callable[[Any], Callable],
    kv: Any,
    h: Any,
    steps: int,
    trail: list | None = None,
) -> tuple[Any, Any]:
    """(q, v) after `steps` sub-steps of h (midpoint_step), each held at its mid configuration, predicted with the
    arm held as the sub-step before it was (at q0 for the first): an exponential midpoint rule in the
    configuration, one M and one C(q, w) w per sub-step; freezing M at q0 for a whole period is what costs a frozen
    prior most on a long arm (docs/training-findings.md). terms(q) -> (v_ss, relax over h) of the arm held at q;
    torque(q) -> (w -> the torques held at the moving velocity w), the first prediction's taken at x0 itself; any
    array namespace.
    trail: gets each sub-step's start, the configuration its predictor holds the arm at and the torques it
    predicts with, then the end's."""
    at, lagged = x0[0], torque(x0[0])(x0[1])
    held = terms(at)
    for _ in range(steps):
        if trail is not None:
            trail.append((x0, at, lagged))
        at = predicted_mid(x0, held, h)
        held = terms(at)
        x0, lagged = midpoint_step(x0, held, torque(at), kv, h, lagged)
    if trail is not None:
        trail.append((x0, at, lagged))
    return x0


def relaxation(m: Tensor, e: Tensor, kv: Tensor) -> Callable[[Tensor], tuple[Tensor, Tensor]]:
    """d -> (kv^-1 M (I - E) d, E d): the lag in q and the decay in v of the arm held with mass matrix M."""

    def relax(d: Tensor) -> tuple[Tensor, Tensor]:
        """kv^-1 M (I - E) d and E d."""
        ed = (e @ d.unsqueeze(-1)).squeeze(-1)
        return (m @ (d - ed).unsqueeze(-1)).squeeze(-1) / kv, ed

    return relax
