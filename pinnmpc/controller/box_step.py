"""The box-constrained Gauss-Newton step: from the normal equations and the input bounds to the step, in numpy.

Both Gauss-Newton solvers (single shooting and lifted) take their steps here; they differ only in how
they build J^T J and the gradient.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.linalg.lapack import dpotrf, dpotrs

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
    if u.shape[0] == 1:
        one = _newton_one(jtj[0], grad[0], u[0], *_rows(lo, hi, u), damping)
        if one is not None:
            return one
    tol = BOUND_TOL * (hi - lo)  # "at a bound" up to rounding: steps aimed at a bound land within it
    fixed = ((u - lo <= tol) & (grad > 0)) | ((hi - u <= tol) & (grad < 0))
    pgrad_max = np.abs(np.where(fixed, 0.0, grad)).max(-1)
    hess = jtj.copy()
    diagonal = np.einsum("bii->bi", hess)  # a writable view
    diagonal += damping * np.maximum(diagonal.mean(-1, keepdims=True), 1e-30)
    delta = masked_solve(hess, grad, fixed)  # one problem came here only where _newton_one's factor failed
    moved = u + delta
    cut = (~fixed & ((moved > hi) | (moved < lo))).any(-1)
    if cut.any():
        delta = active_set_path(hess, grad, fixed, u, lo, hi)
    # ||r||^2 - ||r + J delta||^2 = -(grad . delta + delta^T J^T J delta)
    predicted = -np.einsum("bi,bi->b", delta, grad + np.matmul(jtj, delta[..., None])[..., 0])
    return BoxStep(delta, pgrad_max, predicted, cut)


def _newton_one(
    jtj: np.ndarray, grad: np.ndarray, u: np.ndarray, lo: np.ndarray, hi: np.ndarray, damping: float
) -> BoxStep | None:
    """newton_step of one problem (jtj (n, n), the rest (n,)) on 1-D arrays, where a sample's few small numpy calls
    cost more than their arithmetic; None where its free block is not positive definite (the batch path decides)."""
    tol = BOUND_TOL * (hi - lo)
    fixed = ((u - lo <= tol) & (grad > 0)) | ((hi - u <= tol) & (grad < 0))
    pgrad_max = np.abs(np.where(fixed, 0.0, grad)).max()
    hess = jtj.copy()
    n = hess.shape[0]
    hess.flat[:: n + 1] += damping * max(hess.diagonal().mean(), 1e-30)
    one = _path_one(hess, grad, fixed, u, lo, hi)
    if one is None:
        return None
    delta, cut = one
    predicted = -(delta @ (grad + jtj @ delta))
    return BoxStep(delta[None], np.array([pgrad_max]), np.array([predicted]), np.array([cut]))


def active_set_path(
    hess: np.ndarray, grad: np.ndarray, fixed: np.ndarray, u: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> np.ndarray:
    """Piecewise-linear path of the primal active-set method: Newton direction on the free variables,
    cut at the first bound it meets, which joins the fixed ones; for steps a bound cuts short."""
    one = _path_one(hess[0], grad[0], fixed[0], u[0], *_rows(lo, hi, u)) if u.shape[0] == 1 else None
    if one is not None:
        return one[0][None]
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


def _rows(lo: np.ndarray | float, hi: np.ndarray | float, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The first problem's bounds, however lo and hi broadcast against u (B, n)."""
    if isinstance(lo, np.ndarray) and isinstance(hi, np.ndarray) and lo.shape == hi.shape == u.shape:
        return lo[0], hi[0]  # rows already: np.broadcast_to's Python wrapper costs more than the view
    return np.broadcast_to(lo, u.shape)[0], np.broadcast_to(hi, u.shape)[0]


def _path_one(
    hess: np.ndarray, grad: np.ndarray, fixed: np.ndarray, u: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> tuple[np.ndarray, bool] | None:
    """The Newton step of one problem on its free variables and, where a bound cuts it short, active_set_path's
    path on the same Cholesky factor of their block: a bound met on the way joins as a constraint of the bordered
    system (through its Schur complement, as small as the bounds met), so a segment costs triangular solves where the
    batched path factors again. The step and whether a bound cut it; None where that block is not positive
    definite."""
    free = np.flatnonzero(~fixed)
    if not free.size:
        return np.zeros_like(u), False
    every = free.size == u.size  # nothing fixed: the whole problem, no gathers
    sub = hess if every else hess[np.ix_(free, free)]
    factor, info = dpotrf(sub, lower=0, clean=0)
    if info != 0:
        return None
    room_hi, room_lo = (hi - u, lo - u) if every else ((hi - u)[free], (lo - u)[free])
    step, model_grad = np.zeros(len(free)), grad if every else grad[free]  # the path so far, grad + 2 H step
    active = np.ones(len(free), dtype=bool)
    held = np.empty(0, dtype=np.intp)  # positions in free of the variables fixed on the way
    columns = np.empty((len(free), 0))  # K^-1 E: the factor's solves of their unit vectors
    cut = False
    for _ in range(len(free) + 1):
        direction = dpotrs(factor, -0.5 * model_grad)[0]
        if held.size:  # the bordered system's solution: E^T d = 0 on the held variables
            direction -= columns @ np.linalg.solve(columns[held], direction[held])
            direction[held] = 0.0
        room = np.where(direction > 0, room_hi - step, room_lo - step)
        moving = active & (direction != 0)
        ratio = np.full(len(free), np.inf)  # the fraction of the direction to each bound, where it moves
        np.divide(room, direction, out=ratio, where=moving)
        np.maximum(ratio, 0.0, out=ratio, where=moving)
        first = ratio.min()
        length = min(first, 1.0)
        step += length * direction
        model_grad = model_grad + 2.0 * length * (sub @ direction)
        if not first < 1.0:  # the whole step fits (or NaNs came in: no bound to meet)
            break
        cut = True
        met = np.flatnonzero(ratio <= first)
        active[met] = False
        held = np.concatenate((held, met))
        units = np.zeros((len(free), len(met)))
        units[met, np.arange(len(met))] = 1.0
        columns = np.hstack((columns, dpotrs(factor, units)[0]))
    if every:
        return step, cut
    delta = np.zeros_like(u)
    delta[free] = step
    return delta, cut


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
