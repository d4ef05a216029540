"""The held arm's decay over a span, E = exp(-M^-1 kv h), in CasADi SX for the compiled priors
(pinnmpc.surrogate.prior), through a symmetric matrix.

With Kh = kv^1/2, M^-1 kv = Kh^-1 S Kh for the symmetric positive definite S = Kh M^-1 Kh = W^T W, W = L^-1 Kh
(L the Cholesky factor of M, so W is lower triangular), hence E = Kh^-1 exp(-S h) Kh. Every power of S and every
product of two polynomials in it is symmetric: the Taylor series and its squarings need only upper triangles (4/7
of a general product's work on 7 joints), and Cholesky replaces a general solve. The series' error is then the
scalar one at S's eigenvalues: with p the Taylor polynomial, max over l in [-rho, 0] of |p(l / 2^s)^(2^s) - e^l|
(rho the largest eigenvalue of S h), and its derivative's for a Jacobian by AD (Daleckii-Krein). A stiff mode's
series error is damped by the squarings after it, so fewer squarings meet a tolerance than a norm bound asks for
(docs/design.md).
"""

from __future__ import annotations

import math

import casadi as ca
import numpy as np

TAYLOR_DEGREE = 12  # terms of exp(X / 2^s) before squaring (6 products, Paterson-Stockmeyer)
TOLERANCE = 1e-14  # the largest error of the series and of its derivative on [-rho, 0] (before the Kh scaling)
GRID = 20001  # points of [-rho, 0] the scalar error is checked at
MAX_SQUARINGS = 24  # the search's end: past it rounding has long outgrown the series' error


def series_error(rho: float, squarings: int) -> float:
    """max over l in [-rho, 0] of the error of p(l / 2^s)^(2^s) and of its derivative against e^l."""
    lam = np.linspace(-rho, 0.0, GRID)
    x = lam / 2.0**squarings
    terms = [x**k / math.factorial(k) for k in range(TAYLOR_DEGREE + 1)]
    p, dp = sum(terms), sum(terms[:-1])  # p' is the series one degree shorter
    power = 2**squarings
    value, slope = p**power, p ** (power - 1) * dp
    exact = np.exp(lam)
    return float(max(np.abs(value - exact).max(), np.abs(slope - exact).max()))


def squarings(rho: float) -> int:
    """The fewest squarings that keep the series within TOLERANCE for eigenvalues of S h up to rho; where the
    rounding that every squaring doubles keeps all above it (a very stiff arm), the count with the least error."""
    if not (math.isfinite(rho) and rho >= 0):
        raise ValueError(f"the held arm's largest rate times the span is {rho}; expected a finite number >= 0")
    errors = []
    for s in range(MAX_SQUARINGS):
        errors.append(series_error(rho, s))
        if errors[-1] <= TOLERANCE:
            return s
    return int(np.argmin(errors))


def symmetric_product(a: ca.SX, b: ca.SX) -> ca.SX:
    """a b for n x n a, b whose product is known to be symmetric: its upper triangle, mirrored."""
    n = a.shape[0]
    out = ca.SX(n, n)
    for i in range(n):
        for j in range(i, n):
            out[i, j] = out[j, i] = ca.dot(a[i, :].T, b[:, j])
    return out


def symmetric_expm(x: ca.SX, squarings: int) -> ca.SX:
    """exp(x 2^s) for symmetric x: the Taylor series in powers of x^3 with coefficients in I, x, x^2
    (Paterson-Stockmeyer), then s squarings, every product symmetric."""
    block, eye = 3, ca.SX.eye(x.shape[0])
    square = symmetric_product(x, x)
    powers, cube, out = [eye, x, square], symmetric_product(square, x), None
    for j in range(TAYLOR_DEGREE // block, -1, -1):  # B_j = sum_i x^i / (3j + i)!
        b = sum((powers[i] / math.factorial(block * j + i) for i in range(block) if block * j + i <= TAYLOR_DEGREE), 0)
        out = b if out is None else symmetric_product(out, cube) + b
    for _ in range(squarings):
        out = symmetric_product(out, out)
    return out


def scaled_inverse_factor(m: ca.SX, kh: np.ndarray) -> ca.SX:
    """W = L^-1 Kh, L the Cholesky factor of M: lower triangular, W^T W = Kh M^-1 Kh."""
    n = m.shape[0]
    low = ca.chol(m).T  # CasADi's factor is upper: M = R^T R
    w = ca.SX(n, n)
    for j in range(n):  # forward substitution, column by column; W's column j is zero above row j
        for i in range(j, n):
            rest = sum((low[i, k] * w[k, j] for k in range(j, i)), 0)
            w[i, j] = ((kh[j] if i == j else 0) - rest) / low[i, i]
    return w


def decay(m: ca.SX, kv: np.ndarray, span: float, count: int) -> ca.SX:
    """E = exp(-M^-1 kv span) = Kh^-1 exp(-S span) Kh, with `count` squarings (squarings(rho))."""
    n, kh = m.shape[0], np.sqrt(kv)
    w = scaled_inverse_factor(m, kh)
    s = ca.SX(n, n)
    for a in range(n):
        for b in range(a, n):  # (W^T W)_ab: W is zero above its diagonal, so rows from max(a, b) on
            s[a, b] = s[b, a] = sum((w[i, a] * w[i, b] for i in range(max(a, b), n)), 0)
    p = symmetric_expm(-s * (span / 2**count), count)
    return p * ca.DM(np.outer(1 / kh, kh))
