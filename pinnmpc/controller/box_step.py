"""The box-constrained Gauss-Newton step: from the normal equations and the input bounds to the step, in numpy.

Both Gauss-Newton solvers (single shooting and lifted) take their steps here; they differ only in how
they build J^T J and the gradient.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

BOUND_TOL = 1e-12  # relative to the box width: closer than this to a bound counts as on it


class BoxStep(NamedTuple):
    """A step within the box and what the stopping tests need of it."""

    delta: np.ndarray  # (B, n) the step
    pgrad_max: np.ndarray  # (B,) the projected gradient's max-norm at the start
    predicted: np.ndarray  # (B,) the cost decrease the Gauss-Newton model predicts for the step
    cut: np.ndarray  # (B,) bool: whether a bound cut the Newton step short


def normal_equations(r: np.ndarray, jac: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """J^T J (B, n, n) and the cost gradient 2 J^T r (B, n) of residuals r (B, m) with Jacobian jac (B, m, n):
    all newton_step needs of a least-squares problem."""
    jt = jac.swapaxes(-1, -2)
    return jt @ jac, 2.0 * np.matmul(jt, r[..., None])[..., 0]


def newton_step(
    jtj: np.ndarray, grad: np.ndarray, u: np.ndarray, lo: np.ndarray, hi: np.ndarray, damping: float
) -> BoxStep:
    """Gauss-Newton step within the box [lo, hi], by a primal active set on the (convex) Gauss-Newton model
    1/2 d^T (2 J^T J) d + grad^T d: a step that never leaves the box, so no constrained QP solver is needed.

    Variables at a bound with the gradient pointing out start fixed. From there the free variables
    move along the model's Newton direction until one of them meets a bound; that one is fixed and
    the path goes on, until a full Newton step stays inside (at most n segments, usually one).
    The model decreases along every segment. damping: Levenberg-Marquardt damping relative to the
    mean diagonal of J^T J.
    """
    tol = BOUND_TOL * (hi - lo)  # "at a bound" up to rounding: steps aimed at a bound land within it
    fixed = ((u - lo <= tol) & (grad > 0)) | ((hi - u <= tol) & (grad < 0))
    pgrad_max = np.abs(np.where(fixed, 0.0, grad)).max(-1)
    hess = jtj.copy()
    diagonal = np.einsum("bii->bi", hess)  # a writable view
    diagonal += damping * np.maximum(diagonal.mean(-1, keepdims=True), 1e-30)
    delta = masked_solve(hess, grad, fixed)
    moved = u + delta
    cut = (~fixed & ((moved > hi) | (moved < lo))).any(-1)
    if cut.any():
        delta = active_set_path(hess, grad, fixed, u, lo, hi)
    # ||r||^2 - ||r + J delta||^2 = -(grad . delta + delta^T J^T J delta)
    predicted = -np.einsum("bi,bi->b", delta, grad + np.matmul(jtj, delta[..., None])[..., 0])
    return BoxStep(delta, pgrad_max, predicted, cut)


def active_set_path(
    hess: np.ndarray, grad: np.ndarray, fixed: np.ndarray, u: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> np.ndarray:
    """Piecewise-linear path of the primal active-set method: Newton direction on the free variables,
    cut at the first bound it meets, which joins the fixed ones; for steps a bound cuts short."""
    delta, fixed, done = np.zeros_like(u), fixed.copy(), np.zeros(u.shape[0], dtype=bool)
    for _ in range(u.shape[-1] + 1):
        model_grad = grad + 2.0 * np.matmul(hess, delta[..., None])[..., 0]
        direction = np.where(done[:, None], 0.0, masked_solve(hess, model_grad, fixed))
        room = np.where(direction > 0, hi - u - delta, lo - u - delta)
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(~fixed & (direction != 0), np.maximum(room / direction, 0.0), np.inf)
        first = ratio.min(-1)
        length = np.minimum(first, 1.0)
        delta += length[:, None] * direction
        fixed |= (ratio <= first[:, None]) & (first < 1.0)[:, None]
        done |= first >= 1.0
        if done.all():
            break
    return delta


def masked_solve(hess: np.ndarray, grad: np.ndarray, fixed: np.ndarray) -> np.ndarray:
    """Newton direction of the model 1/2 d^T (2 hess) d + grad^T d on the free variables (0 on the fixed), batched
    in one solve whatever each problem's active set."""
    if not fixed.any():
        return np.linalg.solve(hess, -0.5 * grad[..., None])[..., 0]
    if hess.shape[0] == 1:  # one problem: the free variables' own system, smaller than the masked whole
        free, out = np.flatnonzero(~fixed[0]), np.zeros_like(grad)
        out[0, free] = np.linalg.solve(hess[0][np.ix_(free, free)], -0.5 * grad[0, free])
        return out
    free = ~fixed
    m = hess * (free[:, :, None] & free[:, None, :])
    np.einsum("bii->bi", m)[...] += fixed
    return np.linalg.solve(m, np.where(fixed, 0.0, -0.5 * grad)[..., None])[..., 0]
