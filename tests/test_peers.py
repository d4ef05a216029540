"""The network as its peers run it: traced whole by torch (what l4casadi builds from, with nothing read from a tensor
into Python) and as the classical NMPC's transcription (controller.transcription=network, CasADi's exact Jacobian)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.fx.experimental.proxy_tensor import make_fx

from pinnmpc import load_surrogate, load_system
from pinnmpc.controller.classical.nmpc import build_casadi_nmpc
from pinnmpc.surrogate.prior import ArmPrior
from pinnmpc.surrogate.traced import TracedFlow
from pinnmpc.systems.sampling import random_pairs

ARM = load_system("planar3")
KIND = "midpoint_arm"  # sub-steps, each at its own configuration


def rows(surrogate, n: int, seed: int) -> torch.Tensor:
    """(x0, u) side by side, uniform over the network's training box."""
    x0, u = random_pairs(ARM if surrogate.nx == 6 else load_system("powercube"), n, seed)
    return torch.cat((x0, u), -1).double()


def test_a_traced_network_with_a_prior_is_the_network_at_inputs_it_was_not_traced_at() -> None:
    """planar3's shipped network (frozen-arm prior): its values and Jacobians traced by make_fx are its own at fresh
    inputs (the prior's compiled C path, taken outside traceable(), was baked in as constants: 3e-2 off)."""
    surrogate = load_surrogate(system="planar3")
    flow, traced_at, fresh = TracedFlow(surrogate), rows(surrogate, 4, 0), rows(surrogate, 4, 1)
    value = make_fx(flow)(traced_at)
    jacobian = make_fx(torch.func.vmap(torch.func.jacrev(flow)))(traced_at)
    x0, u = fresh[:, :6], fresh[:, 6:]
    x1, a, b = surrogate.step_with_jacobian(x0, u)
    torch.testing.assert_close(value(fresh), surrogate.step(x0, u), rtol=0, atol=1e-12)
    torch.testing.assert_close(jacobian(fresh), torch.cat((a, b), -1), rtol=0, atol=1e-10)


def test_a_sub_stepped_prior_runs_under_torch_transforms_and_agrees_with_itself() -> None:
    """midpoint_arm (sub-steps up to the longest t): traceable() fixes their count from t_max, so vmap (which
    refuses reading a tensor's value) runs it, with the values and time derivatives of the untraced prior."""
    prior = ArmPrior(ARM, KIND, t_max=0.125)
    x0, u = (a.double() for a in random_pairs(ARM, 8, 2))
    t = torch.linspace(0.0, 0.125, 8, dtype=torch.float64).unsqueeze(-1)
    with pytest.raises(RuntimeError):  # the memo reads data pointers, the sub-steps the longest t
        torch.func.vmap(prior)(t, x0, u)
    with prior.traceable():
        x, dx = torch.func.vmap(prior)(t, x0, u)
    ref_x, ref_dx = prior(t, x0, u)
    torch.testing.assert_close(x, ref_x, rtol=0, atol=1e-12)
    torch.testing.assert_close(dx, ref_dx, rtol=0, atol=1e-10)
    with pytest.raises(ValueError, match="a traced midpoint_arm prior needs t_max"), ArmPrior(ARM, KIND).traceable():
        pass


def test_the_classical_nmpc_on_the_network_predicts_with_the_networks_flow_map() -> None:
    """transcription=network: the OCP's F and F_sens are the network's x(tau) and Jacobian to rounding; a network
    for another arm is refused in one line."""
    system = load_system("powercube")
    surrogate = load_surrogate(system="powercube")
    ocp = {"transcription": "network", "horizon": 3, "Q": [1.0, 1.0, 0.0, 0.0], "R": [1e-3, 1e-3], "codegen": False}
    nmpc = build_casadi_nmpc(ocp, system)
    assert nmpc.describe()["transcription"] == "network"
    xu = rows(surrogate, 5, 3).numpy()
    x0, u = xu[:, :4], xu[:, 4:]
    x1, a, b = (np.asarray(v) for v in nmpc.ocp.F_sens.map(5)(x0.T, u.T))
    ref = [v.numpy() for v in surrogate.step_with_jacobian(torch.from_numpy(x0), torch.from_numpy(u))]
    np.testing.assert_allclose(x1.T, ref[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.reshape(4, 5, 4).transpose(1, 0, 2), ref[1], rtol=0, atol=1e-10)
    np.testing.assert_allclose(b.reshape(4, 5, 2).transpose(1, 0, 2), ref[2], rtol=0, atol=1e-10)
    from pinnmpc.surrogate.checkpoint import shipped

    with pytest.raises(ValueError, match=r"controller.network=.* maps 6 states and 3 inputs; the arm powercube has 4"):
        build_casadi_nmpc({**ocp, "network": str(shipped("planar3"))}, system)
