"""A physics prior for the flow map: the arm frozen at its start configuration, solved exactly.

Over one control period the joint velocities of a damped arm relax towards a steady state with time constants
from M(q)^-1 kv (planar3: 2 ms to 0.12 s), which is most of x(t). Held at q0, without Coriolis and Coulomb terms,
the arm is the linear system M(q0) dv/dt = c0 - kv v, dq/dt = v (kv diagonal), whose flow is closed-form:

    v(t) = v_ss + E(t) (v0 - v_ss),   q(t) = q0 + v_ss t + kv^-1 M (I - E(t)) (v0 - v_ss),
    E(t) = exp(-A t),   A = M^-1 kv,   v_ss = kv^-1 c0.

A network that learns only what this misses (configuration change, Coriolis, Coulomb friction) fits the flow
several times closer on the same budget (docs/training-findings.md). Kind `frozen_arm_friction` adds the arm's dry
friction at the moving velocity: two sub-steps, each the same exact solve with the friction held at a predicted mean
velocity (friction_substeps); an arm without dry friction gets the plain flow. Kind `frozen_arm_moving` holds the
Coriolis and centrifugal torques C(q0, w) w at the moving velocity in the same sub-steps too. Kind `midpoint_arm`
holds the arm per sub-step at its predicted mid configuration instead of q0 (M, gravity, drive and C taken there;
midpoint_substeps): freezing M at q0 is what a frozen prior misses most on a long arm. No parameters: torch for
training (memoised, since full-batch training evaluates it on the same points every step) and CasADi compiled to C,
with its exact Jacobian (by AD, or by eigendecomposition on larger arms: pinnmpc.surrogate.prior_eigen; midpoint_arm
on larger arms: the frozen arm's Jacobian stands in, docs/design.md), for the controller's numpy path.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np
import torch
from omegaconf import OmegaConf
from torch import Tensor, nn

from pinnmpc.surrogate import matrix_exp
from pinnmpc.surrogate.prior_stand_in import held_inertia_jacobian, steady_velocity_jacobian
from pinnmpc.surrogate.substeps import (
    friction_substeps,
    midpoint_step,
    midpoint_substeps,
    predicted_mid,
    relaxation,
)

KINDS = ("frozen_arm", "frozen_arm_friction", "frozen_arm_moving", "midpoint_arm")  # model.prior values besides
#   null: the arm's dry friction settled in c0, or held per sub-step at the moving velocity (friction_substeps; arms
#   without dry friction: the same flow as frozen_arm), or the same with the Coriolis and centrifugal torques
#   C(q0, w) w too, or with M, gravity and the Coriolis torques re-taken per sub-step at its predicted mid
#   configuration (midpoint_substeps)
FRICTION_STEPS = 2  # exponential Heun sub-steps of frozen_arm_friction over a period: the predicted end velocity's
#   friction, averaged with the start's, per sub-step (docs/training.md)
MIDPOINT_STEPS = 6  # sub-steps of midpoint_arm over a period, each with its own configuration: its miss falls as
#   h^2; with 6 the Panda's prior alone is at 0.54x its one-step targets at worst, with 4 1.08x
#   (docs/training-findings.md)
SQUARING_NORM = 0.5  # the largest 1-norm of X / 2^s the export's general Taylor series (degree
#   matrix_exp.TAYLOR_DEGREE) is trusted at: its remainder is then ~1e-14
RATE_MARGIN = 1.5  # the largest rate of M^-1 kv sampled over the box, times this, is what squarings plan for
MEMO_SIZE = 8  # input sets kept, least recently used out first (collocation, anchors, validation, and the data
#   loss's t = 0, new at every step): each holds its inputs alive
EIGEN_FROM_JOINTS = 5  # arms with this many joints or more differentiate the prior by eigendecomposition
#   (pinnmpc/surrogate/prior_eigen.py), smaller ones by CasADi's AD through the series: the cheaper of the two
#   (docs/design.md)


def tensor_key(*tensors: Tensor) -> tuple[Any, ...]:
    """Identity of the inputs: storage, layout and version (the memo holds the tensors, so no storage is reused)."""
    return tuple((a.data_ptr(), a.dtype, tuple(a.shape), a.stride(), a._version) for a in tensors)


@dataclass(frozen=True)
class CompiledPrior:
    """The prior at a fixed tau for numpy rows x0 (B, nx), u (B, nu)."""

    value: Callable[[np.ndarray, np.ndarray], list[np.ndarray]]  # -> [x_p (B, nx)]
    with_jacobian: Callable[[np.ndarray, np.ndarray], list[np.ndarray]]  # -> [x_p, J (B, nx (nx + nu)) row-major]
    stand_in_jacobian: bool = False  # J stands in for the derivative of x_p (pinnmpc.surrogate.prior_stand_in)
    jacobian: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None  # -> J alone, where another function
    #   than the value's gives it (the stand-in): a caller then takes every row's value in one call


class ArmPrior(nn.Module):
    """The physics prior x_p(t) of a URDF arm (see the module docstring), of the kind model.prior names (KINDS: the
    arm frozen at q0, with its friction or moving torques, or re-linearised at midpoints): a System, its `dynamics`
    description (what a network's config stores) or the name of a shipped system."""

    def __init__(self, system: Any, kind: str = "frozen_arm", t_max: float | None = None) -> None:
        super().__init__()
        from pinnmpc.systems import RigidArm, build_system, load_system

        if isinstance(system, Mapping):
            arm = build_system(OmegaConf.create(dict(system)))
        else:
            arm = load_system(system) if isinstance(system, str) else system
        system = getattr(arm, "name", system)
        if not isinstance(arm, RigidArm):
            raise ValueError(
                f"model.prior='frozen_arm' needs an arm from a URDF (a RigidArm); system={system!r} is "
                f"{type(arm).__name__}: set system.network.prior=null"
            )
        if not all(k > 0 for k in arm.linear_gain):
            raise ValueError(
                f"model.prior='frozen_arm' needs a positive viscous coefficient or servo gain on every joint; "
                f"{system} has {list(arm.linear_gain)}: set system.network.prior=null"
            )
        check_prior(kind)
        self.arm, self.nq, self.kind = arm, arm.nq, kind
        self.midpoint = kind == "midpoint_arm"  # M, gravity and C re-taken per sub-step (midpoint_substeps)
        # C(q0, w) w held per sub-step with friction, unless the servo holds it (a payload's share left to the network)
        self.coriolis = kind in ("frozen_arm_moving", "midpoint_arm") and not arm.compensates_bias
        moving = self.coriolis or (
            kind == "frozen_arm_friction" and bool(getattr(arm, "coulomb", None)) and any(arm.coulomb)
        )
        self.steps = MIDPOINT_STEPS if self.midpoint else FRICTION_STEPS if moving else 0  # sub-steps with moving
        #   torques; 0: one exact solve
        self._coriolis_c: ca.Function | None = None  # C(q, w) w in SX, built once
        self.kv = torch.tensor(arm.linear_gain, dtype=torch.float64)  # float64 whatever the network's dtype
        self._memo: dict[tuple[Any, ...], tuple[tuple[Tensor, ...], Tensor, Tensor]] = {}
        self._compiled: dict[float, CompiledPrior] = {}  # per tau: every numpy flow of this network shares one
        self._terms_c: Callable[[np.ndarray, np.ndarray], list[np.ndarray]] | None = None  # M, c0 in C (no graph)
        self.t_max = t_max  # s: the longest t asked for (the network's); fixes the sub-steps while traced
        self._traced = False  # within traceable(): torch operations only

    def moving_torque(self, q0: Any) -> Callable[[Any], Any]:
        """w -> the torques each sub-step holds at the moving velocity w: the dry friction, and for frozen_arm_moving
        C(q0, w) w; q0 a tensor (adam) or a CasADi expression."""
        if not self.coriolis:
            return self.arm.dry_friction
        if isinstance(q0, Tensor):  # adam's torch model lives on the CPU
            return lambda w: self.arm.dry_friction(w) + self.arm.coriolis_torque(q0.cpu(), w.cpu()).to(w.device)
        if self._coriolis_c is None:
            self._coriolis_c = self.arm.casadi_coriolis()
        coriolis = self._coriolis_c
        return lambda w: self.arm.dry_friction(w) + coriolis(q0, w)

    @property
    def stand_in_jacobian(self) -> bool:
        """Whether the compiled Jacobian stands in for x_p's (prior_stand_in): midpoint_arm on a long arm."""
        return self.midpoint and self.nq >= EIGEN_FROM_JOINTS

    def __deepcopy__(self, memo: dict) -> ArmPrior:
        """Shared, not copied: it has no state to diverge (its robot model holds modules that do not copy)."""
        return self

    @contextmanager
    def traceable(self) -> Iterator[None]:
        """Within: torch operations only (adam's torch model, no memo, as many sub-steps as t_max asks), so that a
        tracer (torch.fx's make_fx, which l4casadi uses; torch.jit.trace) records the whole flow, nothing baked in."""
        if self.steps and self.t_max is None:
            raise ValueError(f"a traced {self.kind} prior needs t_max (the longest t) to fix its sub-steps")
        before, self._traced = self._traced, True
        try:
            yield
        finally:
            self._traced = before

    def _count(self, t: Tensor) -> int:
        """Sub-steps of h on the grid up to the batch's longest t (traced: up to t_max, read from no tensor)."""
        top = self.t_max if self._traced else float(t.max()) if t.numel() else 0.0  # an empty batch has no t
        return max(self.steps, math.floor(top / (self.arm.tau / self.steps)) + 1)  # t_max is a little beyond tau

    def _terms(self, q: Tensor, u: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """M, A = M^-1 kv and v_ss (float64, flat batch): through adam in torch where a graph is wanted, else the
        same adam model's CasADi form compiled to C (adam's per-call cost in torch dominates small batches, such as
        a surrogate stepping one state)."""
        if self._traced or q.requires_grad or u.requires_grad:  # adam's model lives on the CPU; copies differentiate
            m, c0 = (a.to(q.device) for a in self.arm.frozen_terms(q.cpu(), u.cpu(), settled=not self.steps))
        else:
            rows = self._compiled_terms()(q.cpu().numpy(), u.cpu().numpy())
            m, c0 = (torch.from_numpy(a).to(q.device) for a in rows)
            m = m.reshape(-1, self.nq, self.nq)  # M is symmetric: its column-major vec reads back as M
        kv = self.kv.to(q.device)
        a = torch.cholesky_solve(torch.diag_embed(kv.expand_as(q)), torch.linalg.cholesky(m))  # M is SPD
        return m, a, c0 / kv

    def _suffix(self) -> str:
        """Name suffix of the compiled functions per flow: one solve, moving friction, with Coriolis too."""
        return "_midpoint" if self.midpoint else "_coriolis" if self.coriolis else "_moving" if self.steps else ""

    def _compiled_terms(self) -> Callable[[np.ndarray, np.ndarray], list[np.ndarray]]:
        """(q, u) rows -> [vec M, c0] rows, compiled once."""
        if self._terms_c is None:
            from pinnmpc.systems.compiled import BatchedFunction, compile_functions

            q, u = ca.SX.sym("q", self.nq), ca.SX.sym("u", self.nq)
            m, c0 = self.arm.casadi_frozen_terms(settled=not self.steps)(q, u)
            name = f"{self.arm.name}_frozen_terms_value{self._suffix()}"
            f = ca.Function(name, [q, u], [ca.densify(ca.vec(m)), c0], {"cse": True})
            self._terms_c = BatchedFunction(compile_functions(name, [f], opt="-O2")[name])
        return self._terms_c

    def _solve(self, t: Tensor, x0: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """x_p(t) and dx_p/dt in float64 for flat inputs."""
        n = self.nq
        q0, v0 = x0[:, :n], x0[:, n:]
        if self.midpoint:
            return self._solve_midpoint(t, (q0, v0), u)
        m, a, vss = self._terms(q0, u)
        if self.steps:
            return self._solve_moving(t, (q0, v0), m, a, vss)
        e = torch.linalg.matrix_exp(-a * t.unsqueeze(-1))
        d = (v0 - vss).unsqueeze(-1)
        v = vss + (e @ d).squeeze(-1)
        q = q0 + vss * t + (m @ (d - e @ d)).squeeze(-1) / self.kv.to(q0.device)
        return torch.cat((q, v), -1), torch.cat((v, -(a @ (v - vss).unsqueeze(-1)).squeeze(-1)), -1)

    def _solve_moving(
        self, t: Tensor, x0: tuple[Tensor, Tensor], m: Tensor, a: Tensor, vss: Tensor
    ) -> tuple[Tensor, Tensor]:
        """x_p(t) with the moving torques (friction_substeps), and dx_p/dt by forward-mode AD. The sub-steps sit on a
        fixed grid of h = tau / steps (the arm's tau), the one a period is cut into: the sub-step holding t advances
        by t less its start, later ones by nothing. Within a sub-step x_p is the exact flow of the arm with its
        torques held, so dq_p/dt = v_p at every t and the physics residual sees only what the held torques miss
        (sub-steps of t / steps instead, as the formula reads at tau, would not: the held torques would change
        with t); at t = tau both are the same flow."""
        kv, h = self.kv.to(vss.device), self.arm.tau / self.steps
        count = self._count(t)

        def relax_by(e: Tensor) -> Callable[[Tensor], tuple[Tensor, Tensor]]:
            """d -> (kv^-1 M (I - E) d, E d) for this E."""
            return relaxation(m, e, kv)

        def flow(t: Tensor) -> Tensor:
            """x_p at t (B, 1)."""
            # the sub-step holding t (k h <= t < (k + 1) h) moves with it: one active span, so dx_p/dt is one-sided
            spans = [torch.where(t >= (k + 1) * h, h, torch.where(t >= k * h, t - k * h, 0.0)) for k in range(count)]
            spans = [(s, relax_by(torch.linalg.matrix_exp(-a * s.unsqueeze(-1)))) for s in spans]
            full = relax_by(torch.linalg.matrix_exp(-a * h))
            torque = self.moving_torque(x0[0])
            return torch.cat(friction_substeps(x0, vss, torque, kv, h, full, count, spans), -1)

        return torch.func.jvp(flow, (t,), (torch.ones_like(t),))

    def _solve_midpoint(self, t: Tensor, x0: tuple[Tensor, Tensor], u: Tensor) -> tuple[Tensor, Tensor]:
        """x_p(t) of midpoint_arm and dx_p/dt on _solve_moving's fixed grid: the whole sub-steps before the one
        holding t (midpoint_substeps), then that one's span from its start, differentiated in t by forward-mode AD
        (its mid configuration and held torques are predicted over the whole sub-step, so they do not move with t:
        within it x_p is an exact flow and dq_p/dt = v_p)."""
        kv, h = self.kv.to(u.device), self.arm.tau / self.steps
        count = self._count(t)
        active = sum((t[:, 0] >= k * h).long() for k in range(1, count))

        def terms(q: Tensor) -> tuple[Tensor, Callable]:
            """v_ss and the relaxation over h of the arm held at q."""
            m, a, vss = self._terms(q, u)
            return vss, relaxation(m, torch.linalg.matrix_exp(-a * h), kv)

        trail: list = []  # each sub-step's start, the configuration its predictor holds the arm at, its lagged torques
        last = count - 1 if self._traced else int(active.max()) if t.numel() else 0  # the last sub-step any t is in
        midpoint_substeps(x0, terms, self.moving_torque, kv, h, last, trail)
        rows = torch.arange(t.shape[0], device=t.device)
        pick = lambda rows_k: torch.stack(rows_k)[active, rows]  # noqa: E731  each one's own sub-step
        start = tuple(pick([x[i] for x, _, _ in trail]) for i in (0, 1))
        before, lagged = (pick([entry[i] for entry in trail]) for i in (1, 2))
        mid = predicted_mid(start, terms(before), h)
        m, a, vss = self._terms(mid, u)
        held, torque = (vss, relaxation(m, torch.linalg.matrix_exp(-a * h), kv)), self.moving_torque(mid)

        def flow(t: Tensor) -> Tensor:
            """x_p at t (B, 1)."""
            span = t - active.unsqueeze(-1).to(t.dtype) * h  # to t's dtype first: long * float would be float32
            relax = relaxation(m, torch.linalg.matrix_exp(-a * span.unsqueeze(-1)), kv)
            return torch.cat(midpoint_step(start, held, torque, kv, h, lagged, (span, relax))[0], -1)

        return torch.func.jvp(flow, (t,), (torch.ones_like(t),))

    def forward(self, t: Tensor, x0: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """x_p(t) and dx_p/dt for t (..., 1), x0 (..., nx), u (..., nu), in x0's dtype; x_p(0) = x0."""
        t, x0, u = torch.broadcast_tensors(t, x0[..., :1], u[..., :1])[0], x0, u
        lead, nx = x0.shape[:-1], x0.shape[-1]
        if self._traced or t.requires_grad or x0.requires_grad or u.requires_grad:  # a graph is wanted: no memo
            x, dx = self._solve(*(a.reshape(-1, a.shape[-1]).double() for a in (t, x0, u)))
            return x.to(x0.dtype).reshape(*lead, nx), dx.to(x0.dtype).reshape(*lead, nx)
        key = tensor_key(t, x0, u)
        hit = self._memo.pop(key, None)  # re-inserted below: the least recently used set goes first
        if hit is None:
            with torch.no_grad():
                x, dx = self._solve(*(a.reshape(-1, a.shape[-1]).double() for a in (t, x0, u)))
            if len(self._memo) >= MEMO_SIZE:
                self._memo.pop(next(iter(self._memo)))
            hit = ((t, x0, u), x.to(x0.dtype).reshape(*lead, nx), dx.to(x0.dtype).reshape(*lead, nx))
        self._memo[key] = hit
        return hit[1], hit[2]

    def with_jacobian(self, t: Tensor, x0: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """x_p(t) and d x_p / d(x0, u) (..., nx, nx + nu) by reverse mode (the torch path; numpy has compiled())."""
        with torch.enable_grad():
            xr, ur = x0.detach().double().requires_grad_(True), u.detach().double().requires_grad_(True)
            x, _ = self.forward(t.detach().double(), xr, ur)
            rows = [torch.autograd.grad(x[..., k].sum(), (xr, ur), retain_graph=True) for k in range(x.shape[-1])]
        jac = torch.stack([torch.cat(r, -1) for r in rows], -2)
        return x.detach().to(x0.dtype), jac.to(x0.dtype)

    def squarings(self, tau: float, symmetric: bool = False) -> int:
        """Squarings s of exp(-A tau): general, so that |A tau / 2^s| <= SQUARING_NORM (the export's series);
        symmetric, the fewest the symmetric series needs for A's eigenvalues (pinnmpc.surrogate.matrix_exp). Both over
        the boxes, sampled, with a 1.5x margin."""
        a = self._box_rates()
        if symmetric:
            return matrix_exp.squarings(float(torch.linalg.eigvals(a).real.max()) * tau * RATE_MARGIN)
        norm = float(torch.linalg.matrix_norm(a * tau, ord=1).max()) * RATE_MARGIN
        return max(0, math.ceil(math.log2(norm / SQUARING_NORM)))

    def _box_rates(self, samples: int = 4096) -> Tensor:
        """A = M^-1 kv at configurations sampled over the box (a fixed draw)."""
        from pinnmpc.systems.sampling import random_pairs

        q = random_pairs(self.arm, samples, 0)[0].double()[:, : self.nq]
        with torch.no_grad():
            return self._terms(q, torch.zeros_like(q))[1]

    def compiled(self, tau: float) -> CompiledPrior:
        """x_p(tau), and with its Jacobian, for numpy rows: the value as a fixed Taylor-and-squaring exponential
        compiled to C by CasADi, the Jacobian by CasADi's exact AD through it or, on larger arms, exactly by
        eigendecomposition (pinnmpc.surrogate.prior_eigen), where midpoint_arm's takes a stand-in
        (pinnmpc.surrogate.prior_stand_in); built once per tau and checked against the torch form."""
        if tau in self._compiled:
            return self._compiled[tau]
        period = math.isclose(tau, self.arm.tau, rel_tol=1e-12)
        if self.steps and not self.midpoint and not period:
            raise ValueError(
                f"a {self.kind} prior's sub-steps cut the arm's period ({self.arm.tau} s); a flow over tau={tau} s "
                "would be another function: use the system's tau"
            )
        from pinnmpc.systems.compiled import BatchedFunction, compile_functions

        n, h, kv = self.nq, (self.arm.tau if self.midpoint else tau) / max(1, self.steps), ca.DM(self.kv.numpy())
        s = self.squarings(h, symmetric=True)
        tag = f"{self.arm.name}_frozen_prior{self._suffix()}" + ("" if period else f"_{round(tau * 1e6)}us")
        frozen = self.arm.casadi_frozen_terms(settled=not self.steps)

        def held(q: ca.SX, u: ca.SX, h: float = h) -> tuple[ca.SX, ca.SX, ca.SX]:
            """v_ss, kv^-1 M (I - E) (at q0: dq(tau)/dv0) and E over h of the arm held at q."""
            m, c0 = frozen(q, u)
            e = matrix_exp.decay(m, self.kv.numpy(), h, s)
            return c0 / kv, ca.mtimes(ca.diag(1 / kv), ca.mtimes(m, ca.SX.eye(n) - e)), e

        def held_over(name: str, h: float = h) -> ca.Function:
            """held as a function (q, u) -> (v_ss, L, E) over h, compiled once and called per sub-step."""
            qs, us = ca.SX.sym("q", n), ca.SX.sym("u", n)
            return ca.Function(f"{tag}_{name}", [qs, us], list(held(qs, us, h)), {"cse": True})

        if self.midpoint:  # sub-steps at configurations of their own: the held arm compiled once, called per sub-step
            held_arm = held_over("held")
            x, u = ca.MX.sym("x", 2 * n), ca.MX.sym("u", n)
            xp = ca.vertcat(*self._midpoint_flow(held_over, held_arm, (x, u), tau, h))
        else:
            x, u = ca.SX.sym("x", 2 * n), ca.SX.sym("u", n)
            q0, v0 = x[:n], x[n:]
            vss, lag, e = held(q0, u)
            if self.steps:
                relax = lambda d: (ca.mtimes(lag, d), ca.mtimes(e, d))  # noqa: E731
                xp = ca.vertcat(*friction_substeps((q0, v0), vss, self.moving_torque(q0), kv, h, relax, self.steps))
            else:
                d = v0 - vss
                xp = ca.vertcat(q0 + vss * tau + ca.mtimes(lag, d), vss + ca.mtimes(e, d))
        value = ca.Function(f"{tag}_value", [x, u], [xp], {"cse": True})
        if self.stand_in_jacobian:
            # the Jacobian of the arm frozen at q0 with its inertia held stands in for this one's: the controller's
            # linearisation is that arm's, its model's value exact (an inexact-Jacobian SQP; docs/design.md)
            steady = steady_velocity_jacobian(frozen, kv, f"{tag}_steady")
            if not period:  # the stand-in's held arm over tau / steps, as over the period
                held_arm = held_over("held_j", tau / self.steps)
            held = held_inertia_jacobian(held_arm, steady, self.steps, tau, f"{tag}_held_inertia")
            lib = compile_functions(tag, [value, held], opt="-O2")
            exact, stand_in = BatchedFunction(lib[value.name()]), BatchedFunction(lib[held.name()])
            alone = lambda x0, u: stand_in(x0, u)[0]  # noqa: E731
            fast = CompiledPrior(exact, lambda x0, u: [exact(x0, u)[0], alone(x0, u)], True, alone)
        elif n >= EIGEN_FROM_JOINTS:
            from pinnmpc.surrogate.prior_eigen import EigenPriorJacobian

            lib = compile_functions(tag, [value], opt="-O2")
            jacobian = EigenPriorJacobian(self.arm, tau, self.kv.numpy(), self.steps, self.coriolis, self._suffix())
            fast = CompiledPrior(BatchedFunction(lib[value.name()]), jacobian)
        elif self.steps:  # friction couples v0 and u into the sub-steps: AD along every input
            jac = ca.jacobian(xp, ca.vertcat(x, u))
            full = ca.Function(tag, [x, u], [xp, ca.densify(ca.vec(jac.T))], {"cse": True})
            lib = compile_functions(tag, [value, full], opt="-O2")
            fast = CompiledPrior(BatchedFunction(lib[value.name()]), BatchedFunction(lib[full.name()]))
        else:
            # x_p is linear in (v0, v_ss) given q0: those columns are E's blocks; AD only along q0, through M and E
            by_v0 = ca.vertcat(lag, e)
            by_vss = ca.vertcat(tau * ca.SX.eye(n) - lag, ca.SX.eye(n) - e)
            jac = ca.horzcat(ca.jacobian(xp, q0), by_v0, ca.mtimes(by_vss, ca.jacobian(vss, u)))
            full = ca.Function(
                tag, [x, u], [xp, ca.densify(ca.vec(jac.T))], {"cse": True}
            )  # dense: BatchedFunction's rows
            lib = compile_functions(tag, [value, full], opt="-O2")
            fast = CompiledPrior(BatchedFunction(lib[value.name()]), BatchedFunction(lib[full.name()]))
        self._check_compiled(fast.with_jacobian, tau, jacobian=not self.stand_in_jacobian)
        self._compiled[tau] = fast
        return fast

    def _midpoint_flow(
        self, held_over: Callable, held_arm: ca.Function, xu: tuple[ca.MX, ca.MX], tau: float, h: float
    ) -> tuple[ca.MX, ca.MX]:
        """midpoint_arm's x_p(tau) in CasADi on _solve_midpoint's grid of h: the whole sub-steps before tau, then
        the one holding tau over its span from its start (a period split in two: pinnmpc.surrogate.delayed_command)."""
        (x, u), n, kv = xu, self.nq, ca.DM(self.kv.numpy())

        def terms(q: ca.MX, arm: ca.Function = held_arm) -> tuple[ca.MX, Callable]:
            """v_ss and the relaxation over h (or arm's span) of the arm held at q."""
            vss, lag, e = arm(q, u)
            return vss, lambda d: (ca.mtimes(lag, d), ca.mtimes(e, d))

        whole = math.floor(tau / h + 1e-9)
        span = tau - whole * h
        trail: list = []
        end = midpoint_substeps((x[:n], x[n:]), terms, self.moving_torque, kv, h, whole, trail)
        if span <= 1e-9 * h:
            return end
        start, before, lagged = trail[whole]
        mid = predicted_mid(start, terms(before), h)
        relax = (span, terms(mid, held_over("held_span", span))[1])
        return midpoint_step(start, terms(mid), self.moving_torque(mid), kv, h, lagged, relax)[0]

    def _check_compiled(self, fast: Any, tau: float, samples: int = 8, jacobian: bool = True) -> None:
        """Refuse a compiled prior that disagrees with the torch one (value, and Jacobian unless it stands in for
        this one's) at random points."""
        from pinnmpc.systems.sampling import random_pairs

        x0, u = (a.double() for a in random_pairs(self.arm, samples, 1))
        t = torch.full((samples, 1), tau, dtype=torch.float64)
        xn, jn = fast(x0.numpy(), u.numpy())
        if not jacobian:  # a stand-in Jacobian has no torch form to agree with: the value only, no reverse pass
            with torch.no_grad():
                x = self.forward(t, x0, u)[0]
            off = float(abs(xn - x.numpy()).max() / (1 + abs(x.numpy()).max()))
        else:
            x, jac = self.with_jacobian(t, x0, u)
            off = max(
                float(abs(xn - x.numpy()).max() / (1 + abs(x.numpy()).max())),
                float(abs(jn.reshape(jac.shape) - jac.numpy()).max() / (1 + abs(jac.numpy()).max())),
            )
        if not off < 1e-8:
            raise RuntimeError(
                f"the compiled frozen-arm prior of {self.arm.name} disagrees with its torch form (relative {off:.1e}, "
                "expected < 1e-8): set system.network.prior=null"
            )


def check_prior(kind: str | None) -> None:
    """model.prior must be null or a known kind."""
    if kind is not None and kind not in KINDS:
        raise ValueError(f"model.prior={kind!r}; expected null or one of {list(KINDS)}")
