"""The CasADi side of a URDF arm (RigidArm's): its symbolic dynamics for the classical NMPC, the compiled training
path and the frozen-arm prior's Jacobians, through adam's CasADi backend."""

from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np


class CasadiArm:
    """CasADi functions of the arm: a mixin of RigidArm, whose fields and law (actuation_torque, _bias) they use."""

    def casadi_coriolis(self) -> ca.Function:
        """(q, v) -> C(q, v) v as a CasADi SX function (callable on SX, MX or numbers)."""
        q, v = ca.SX.sym("q", self.nq), ca.SX.sym("v", self.nq)
        c = self._casadi_kindyn().coriolis_term(ca.SX.eye(4), q, ca.SX.zeros(6), v)[6:]
        if self.compensates_bias:
            c = c - self._casadi_kindyn(nominal=True).coriolis_term(ca.SX.eye(4), q, ca.SX.zeros(6), v)[6:]
        c = self.mass_scale * c
        return ca.Function(f"{self.name}_coriolis", [q, v], [c], {"cse": True})

    def casadi_frozen_terms(self, settled: bool = True) -> ca.Function:
        """The same (q, u) -> (M, c0) as a CasADi SX function (adam's CasADi backend)."""
        n = self.nq
        q, u = ca.SX.sym("q", n), ca.SX.sym("u", n)
        m, g, comp = self.casadi_terms(q, ca.SX.zeros(n), gravity=True)
        drive = self._frozen_drive(g, u, comp, settled)
        return ca.Function(f"{self.name}_frozen", [q, u], [m, drive], {"cse": True})

    def casadi_rhs(self) -> ca.Function:
        """dx/dt = f(x, u) as a CasADi SX function (adam's CasADi backend, the joint block of M and h)."""
        n = self.nq
        x, u = ca.SX.sym("x", 2 * n), ca.SX.sym("u", n)
        q, v = x[:n], x[n:]
        m, h, g = self.casadi_terms(q, v)
        acc = ca.solve(m, self.actuation_torque(v, u) - self._bias(h, g))
        return ca.Function(f"{self.name}_rhs", [x, u], [ca.vertcat(v, acc)], {"cse": True})

    def casadi_inverse_dynamics(self, coulomb_width: float | None = None) -> ca.Function:
        """r(q, v, a, u) = M(q) a + h(q, v) - tau(v, u) (SX), as casadi_rhs without M^-1 (no sign(v) term to smooth:
        coulomb_width is the PowerCube's)."""
        q, v, a, u = (ca.SX.sym(name, self.nq) for name in ("q", "v", "a", "u"))
        m, h, g = self.casadi_terms(q, v)
        r = m @ a + self._bias(h, g) - self.actuation_torque(v, u)
        return ca.Function(
            f"{self.name}_inverse_dynamics", [q, v, a, u], [r], ["q", "v", "a", "u"], ["r"], {"cse": True}
        )

    def casadi_terms(self, q: Any, v: Any, gravity: bool = False) -> tuple[Any, Any, Any]:
        """M (armature included), h and what a servo compensates (its gravity, or its bias h with servo_compensation
        'bias'; 0 for torque arms) as CasADi expressions, h and that at v = 0 with gravity=True: what every symbolic
        model of the arm builds on."""
        kd, base = self._casadi_kindyn(), ca.SX.eye(4)
        m = self.mass_scale * kd.mass_matrix(base, q)[6:, 6:]
        if self.armature:
            m = m + ca.diag(ca.DM(self.armature))
        h = kd.gravity_term(base, q)[6:] if gravity else kd.bias_force(base, q, ca.SX.zeros(6), v)[6:]  # gravity: v=0
        servo = self.actuation == "velocity_servo"
        kg = self._casadi_kindyn(nominal=True) if servo and self.payload is not None else kd
        if not servo:
            g = 0
        elif self.servo_compensation == "bias" and not gravity:
            g = h if kg is kd else kg.bias_force(base, q, ca.SX.zeros(6), v)[6:]
        else:
            g = kg.gravity_term(base, q)[6:]
        return m, h, g

    def _casadi_kindyn(self, nominal: bool = False) -> Any:
        """adam's CasADi model of the arm (the other joints locked; nominal: the servo's arm, without the payload)."""
        from adam.casadi import KinDynComputations

        text = self.servo_urdf if nominal else self.model_urdf
        return KinDynComputations(text, list(self.joints), gravity=np.array([*self.gravity, 0, 0, 0]))
