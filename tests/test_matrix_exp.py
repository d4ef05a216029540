"""The compiled priors' decay E = exp(-M^-1 kv h) through the symmetric S = Kh M^-1 Kh
(pinnmpc.surrogate.matrix_exp): exact to rounding on the arms' own mass matrices, with fewer squarings than a norm
bound, and its scalar error criterion honest."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
import scipy.linalg
import torch

from pinnmpc import load_system
from pinnmpc.surrogate import matrix_exp
from pinnmpc.surrogate.prior import ArmPrior
from pinnmpc.systems.sampling import random_pairs


def _mass_matrices(name: str, count: int) -> tuple[ArmPrior, np.ndarray]:
    """The arm's prior and its mass matrices at configurations drawn over the training box."""
    prior = ArmPrior(load_system(name), "midpoint_arm")
    q = random_pairs(prior.arm, count, 5)[0].double()[:, : prior.nq]
    with torch.no_grad():
        m = prior._terms(q, torch.zeros_like(q))[0]
    return prior, m.numpy()


@pytest.mark.parametrize("name", ["planar3", "panda"])
def test_decay_matches_the_exponential_on_the_arms_own_mass_matrices(name: str) -> None:
    prior, masses = _mass_matrices(name, 24)
    kv, h = prior.kv.numpy(), prior.arm.tau / prior.steps
    count = prior.squarings(h, symmetric=True)
    m = ca.SX.sym("m", prior.nq, prior.nq)
    f = ca.Function("decay", [m], [matrix_exp.decay(m, kv, h, count)])
    worst = 0.0
    for mass in masses:
        exact = scipy.linalg.expm(-np.linalg.solve(mass, np.diag(kv)) * h)
        worst = max(worst, float(abs(np.array(f(mass)) - exact).max()))
    # measured: 1e-15 (planar3) to 5e-15 (panda), against the 1e-14 the squarings are planned for
    assert worst < 1e-13, worst
    # the stiff modes' series error is damped by the squarings after it: fewer than a 1-norm bound asks
    assert count < prior.squarings(h)


def test_the_squaring_count_is_the_fewest_that_meets_the_tolerance() -> None:
    for rho in (0.3, 5.0, 18.0, 80.0):
        s = matrix_exp.squarings(rho)
        assert matrix_exp.series_error(rho, s) <= matrix_exp.TOLERANCE
        assert s == 0 or matrix_exp.series_error(rho, s - 1) > matrix_exp.TOLERANCE
    # far stiffer: the rounding each squaring doubles outgrows the tolerance; the count with the least error
    errors = [matrix_exp.series_error(400.0, s) for s in range(matrix_exp.MAX_SQUARINGS)]
    assert min(errors) > matrix_exp.TOLERANCE and matrix_exp.squarings(400.0) == int(np.argmin(errors))
    assert min(errors) < 1e-13
    # the criterion sees what it claims: a series squared too few times misses e^l by far more
    assert matrix_exp.series_error(18.0, 1) > 1e-3


def test_symmetric_product_and_exponential_agree_with_dense_algebra() -> None:
    rng = np.random.default_rng(0)
    a = rng.normal(size=(5, 5))
    s = -(a @ a.T) / 10  # symmetric negative definite, as -S h / 2^s is
    x = ca.SX.sym("x", 5, 5)
    product = ca.Function("p", [x], [matrix_exp.symmetric_product(x, x)])
    assert np.allclose(np.array(product(s)), s @ s, rtol=0, atol=1e-15)
    expm = ca.Function("e", [x], [matrix_exp.symmetric_expm(x, 3)])
    assert np.allclose(np.array(expm(s / 8)), scipy.linalg.expm(s), rtol=0, atol=1e-14)


def test_a_rate_that_is_not_a_finite_number_is_refused() -> None:
    with pytest.raises(ValueError, match="largest rate times the span is inf"):
        matrix_exp.squarings(float("inf"))
