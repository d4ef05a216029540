"""Self-scaled BFGS with a dense inverse Hessian (Urbán et al. 2024; Kiyani et al. 2025) for full-batch PINN training.

L-BFGS keeps a few dozen curvature pairs and forgets them at every stall or redraw of the collocation points; a
network of ~10^4 parameters can afford the whole n x n inverse Hessian, which then survives redraws (the curvature
of the expected residual loss hardly depends on the draw). The self-scaling factor enlarges the inverse Hessian
whenever the line search finds a step too short for it, the fix those papers report for BFGS's slow phases on
PINN losses. The strong Wolfe line search is PyTorch's, the one torch.optim.LBFGS uses.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor
from torch.optim.lbfgs import _strong_wolfe

VARIANTS = ("ssbfgs", "ssbroyden", "bfgs")
HESSIAN_DTYPES = {"float32": torch.float32, "float64": torch.float64}


@dataclass
class Step:
    """One accepted iteration: its curvature pair, H y, the slope -s'g where it started and s'B s (B = H^-1)."""

    s: Tensor
    y: Tensor
    hy: Tensor
    slope: float
    sbs: float  # s' H^-1 s: t * slope for a step along -H g of length t
    first: bool = False  # the first pair after H was (re)built from the identity


class InverseHessian:
    """H = c D + A B': a dense n x n matrix D, a scalar c and the pending low-rank updates A B' (n x k each).

    Each BFGS update scales H and adds a rank-two term; applied one by one they cost two passes over the n x n
    matrix per iteration (read and write), more than the network's loss and gradient at 10^4 parameters. Kept
    aside and folded into D `buffer` updates at a time, an iteration reads D once (its product with a vector).
    """

    def __init__(self, n: int, scale: float, dtype: torch.dtype, device: torch.device, buffer: int) -> None:
        self.D = torch.eye(n, dtype=dtype, device=device)
        self.c = float(scale)
        self.A = torch.zeros(n, 0, dtype=dtype, device=device)
        self.B = torch.zeros(n, 0, dtype=dtype, device=device)
        self.buffer = int(buffer)
        self.dtype = dtype

    def __matmul__(self, v: Tensor) -> Tensor:
        """H v without forming H."""
        out = (self.D @ v).mul_(self.c)
        return out.addmv_(self.A, self.B.T @ v) if self.A.shape[1] else out

    def update(self, UM: Tensor, U: Tensor, tau: float) -> None:
        """H <- H / tau + (U M) U' (M symmetric); folded into D once `buffer` updates are pending."""
        self.c /= tau
        self.A = torch.cat([self.A / tau, UM], dim=1)
        self.B = torch.cat([self.B, U], dim=1)
        if self.B.shape[1] >= 2 * self.buffer:
            self.fold()

    def fold(self) -> None:
        """D <- c D + A B' in one pass over D."""
        self.D.addmm_(self.A, self.B.T, beta=self.c)
        self.c = 1.0
        self.A, self.B = self.A[:, :0], self.B[:, :0]

    def matrix(self) -> Tensor:
        """H itself (folds what is pending)."""
        self.fold()
        return self.D


class SSBFGS(torch.optim.Optimizer):
    """Dense (self-scaled) BFGS over all parameters with a strong Wolfe line search; one `step` runs max_iter
    iterations, like torch.optim.LBFGS, so it drops into the same full-batch training loop."""

    def __init__(
        self,
        params: Any,
        lr: float = 1.0,
        max_iter: int = 50,
        tolerance_grad: float = 1e-9,
        tolerance_change: float = 1e-12,
        variant: str = "ssbfgs",
        hessian_dtype: str = "float64",
        max_params: int = 40_000,
        buffer: int = 16,
    ) -> None:
        if variant not in VARIANTS:
            raise ValueError(f"module.ssbfgs_variant={variant!r}; expected one of {list(VARIANTS)}")
        if isinstance(buffer, bool) or not isinstance(buffer, int) or buffer < 1:
            raise ValueError(f"module.hessian_buffer={buffer!r}; expected a positive integer")
        if hessian_dtype not in HESSIAN_DTYPES:
            raise ValueError(f"module.hessian_dtype={hessian_dtype!r}; expected one of {sorted(HESSIAN_DTYPES)}")
        super().__init__(params, {"lr": lr})
        if len(self.param_groups) != 1:
            raise ValueError("SSBFGS takes one parameter group")
        self._params: list[Tensor] = self.param_groups[0]["params"]
        n = sum(p.numel() for p in self._params)
        if n > max_params:
            gib = n * n * HESSIAN_DTYPES[hessian_dtype].itemsize / 2**30
            raise ValueError(
                f"module.optimizer=ssbfgs keeps a dense {n} x {n} inverse Hessian ({gib:.1f} GiB) for this network; "
                f"expected at most {max_params} trainable parameters (use module.optimizer=lbfgs or a smaller model)"
            )
        self.n = n
        self.max_iter = int(max_iter)
        self.tolerance_grad = float(tolerance_grad)
        self.tolerance_change = float(tolerance_change)
        self.variant = variant
        self.hessian_dtype = HESSIAN_DTYPES[hessian_dtype]
        self.buffer = buffer
        self._ceiling = math.inf

    # -- flat views of the parameters ---------------------------------------------------------------------------
    def _flat_grad(self) -> Tensor:
        """All gradients as one vector (zeros for parameters without one)."""
        return torch.cat([(p.grad if p.grad is not None else torch.zeros_like(p)).reshape(-1) for p in self._params])

    def _flat_params(self) -> Tensor:
        """A copy of all parameters as one vector."""
        return torch.cat([p.detach().reshape(-1) for p in self._params]).clone()

    @torch.no_grad()
    def _set_params(self, flat: Tensor) -> None:
        """Write one vector back into the parameters."""
        offset = 0
        for p in self._params:
            n = p.numel()
            p.copy_(flat[offset : offset + n].view_as(p))
            offset += n

    def _evaluate(self, closure: Callable[[], Tensor], x: Tensor, t: float, d: Tensor) -> tuple[float, Tensor]:
        """Loss and gradient at x + t d (what the line search asks for). A trial step so long that the network
        overflows reads as a huge finite loss with zero slope, so the line search shortens the step instead of
        carrying NaN into the parameters and the inverse Hessian."""
        self._set_params(x + t * d)
        with torch.enable_grad():
            loss = float(closure().detach())
        g = self._flat_grad()
        if not (math.isfinite(loss) and bool(torch.isfinite(g).all())):
            return self._ceiling, torch.zeros_like(g)
        return loss, g

    # -- state ---------------------------------------------------------------------------------------------------
    @property
    def _state(self) -> dict[str, Any]:
        """Optimizer state lives on the first parameter, as torch.optim.LBFGS keeps it."""
        return self.state[self._params[0]]

    def reset(self) -> None:
        """Forget the inverse Hessian (it is rebuilt from the next step's curvature)."""
        self._state.pop("H", None)

    def state_dict(self) -> dict[str, Any]:
        """Everything but the n x n matrix: checkpoints stay small; a resumed run rebuilds it within iterations."""
        sd = super().state_dict()
        sd["state"] = {k: {n: v for n, v in s.items() if n != "H"} for k, s in sd["state"].items()}
        return sd

    def _update(self, H: InverseHessian, step: Step) -> Callable[[Tensor, Tensor], Tensor]:
        """Self-scaled Broyden-family update of the inverse Hessian (a scale plus rank two); returns the map
        H v -> H+ v, so the next direction needs no second product with the n x n matrix.

        H+ = (1/tau) (H - Hy Hy'/y'Hy + phi y'Hy v v') + s s'/y's, v = s/y's - Hy/y'Hy. bfgs: phi = tau = 1;
        ssbfgs: phi = 1, tau = min(1, y's / (-s'g)), below 1 when the curvature along s is smaller than the slope
        predicted (H was too small there); ssbroyden: phi and tau both from the pair (_broyden_parameters). A pair
        that fails the curvature condition is skipped.
        """
        s, y, hy = step.s.to(H.dtype), step.y.to(H.dtype), step.hy
        ys, yhy = float(y @ s), float(y @ hy)
        if not (math.isfinite(ys) and math.isfinite(yhy)) or ys <= 1e-10 * float(s.norm() * y.norm()) or yhy <= 0:
            return lambda hv, v: hv  # keeps H positive definite
        tau, phi = 1.0, 1.0
        if self.variant == "ssbfgs" and step.slope > 0:
            tau = min(1.0, ys / step.slope)
        elif self.variant == "ssbroyden" and step.sbs > 0:
            phi, tau = _broyden_parameters(yhy / ys, step.sbs / ys, self.n, step.first)
        a = 1.0 / ys
        # H+ = H/tau + [s Hy] M [s Hy]' with this 2 x 2 M (the v v' term expanded)
        m = torch.tensor(
            [[(phi * yhy * a * a) / tau + a, -phi * a / tau], [-phi * a / tau, (phi - 1.0) / (tau * yhy)]],
            dtype=H.dtype,
            device=s.device,
        )
        U = torch.stack([s, hy], dim=1)
        Um = U @ m
        H.update(Um, U, tau)
        return lambda hv, v: hv / tau + Um @ (U.T @ v)

    @torch.no_grad()
    def step(self, closure: Callable[[], Tensor]) -> Tensor:  # type: ignore[override]
        """Up to max_iter quasi-Newton iterations on the closure's loss; returns the first loss, as LBFGS does."""
        state = self._state
        state.setdefault("func_evals", 0)
        state.setdefault("n_iter", 0)
        lr = self.param_groups[0]["lr"]
        with torch.enable_grad():
            first = closure()
        loss = float(first.detach())
        g = self._flat_grad()
        state["func_evals"] += 1
        if g.abs().max() <= self.tolerance_grad or not math.isfinite(loss):
            return first
        H: InverseHessian | None = state.get("H")
        hg = None if H is None else H @ g.to(H.dtype)  # H g, carried from iteration to iteration
        x = self._flat_params()
        self._ceiling = abs(loss) * 1e12 + 1e12  # stands for a non-finite trial loss
        for _ in range(self.max_iter):
            if H is None or hg is None:
                d = -g
                t = min(1.0, 1.0 / float(g.abs().sum())) * lr
            else:
                d = -hg.to(g.dtype)
                t = lr
            gtd = float(g @ d)
            if not gtd < -self.tolerance_change:
                if H is None or not gtd >= 0:  # no decrease left to find along d
                    break
                H = hg = None  # not a descent direction: H has lost positive definiteness, start over
                continue
            loss_new, g_new, t, ls_evals = _strong_wolfe(
                lambda x_, t_, d_: self._evaluate(closure, x_, t_, d_), x, t, d, loss, g, gtd
            )
            state["func_evals"] += int(ls_evals)
            state["n_iter"] += 1
            if not loss_new < loss:  # the line search found no decrease (or only overflowing steps): stay, reset H
                self._set_params(x)
                state["rejected"] = state.get("rejected", 0) + 1
                H = hg = None
                break
            s = t * d
            x = x + s
            self._set_params(x)
            y = g_new - g
            fresh = H is None or hg is None
            if fresh:  # the first curvature pair scales the identity (Nocedal and Wright 6.20)
                ys = float(y @ s)
                scale = ys / float(y @ y) if ys > 0 else 1.0
                H = InverseHessian(self.n, scale, self.hessian_dtype, g.device, self.buffer)
                hg = scale * g.to(H.dtype)
            g64 = g_new.to(H.dtype)
            hg_new = H @ g64
            # s' H^-1 s: of the scaled identity for the first pair, else t * slope (s = -t H g)
            sbs = float(s @ s) / H.c if fresh else -gtd * t * t
            apply = self._update(H, Step(s=s, y=y, hy=hg_new - hg, slope=-gtd * t, sbs=sbs, first=fresh))
            hg = apply(hg_new, g64)
            change = abs(loss_new - loss)
            loss, g = loss_new, g_new
            if g.abs().max() <= self.tolerance_grad:
                break
            if s.abs().max() <= self.tolerance_change or change < self.tolerance_change:
                break
        if H is not None:
            state["H"] = H
        else:
            state.pop("H", None)
        return first


def _broyden_parameters(h: float, b: float, n: int, first: bool) -> tuple[float, float]:
    """phi and tau of the self-scaled Broyden update (Al-Baali et al. 2014, as used for PINNs by Urban et al. 2024
    and Kiyani et al. 2025) from h = y'Hy/y's and b = s'H^-1 s/y's: the family parameter kept in the interval where H
    stays positive definite and well scaled, and the scale that keeps its determinant in check."""
    a = max(b * h - 1.0, 0.0)  # >= 0 for positive definite H (Cauchy-Schwarz); rounding can make it slightly negative
    if a <= 1e-12:  # y is an eigenvector's image: every member of the family is the same update
        return 1.0, min(1.0, 1.0 / b)
    rho_minus = min(1.0, h * (1.0 - math.sqrt(a / (1.0 + a))))
    theta = max((rho_minus - 1.0) / a, min(1.0 / rho_minus, (1.0 - b) / b))
    sigma = 1.0 + a * theta  # > 0: theta >= (rho_minus - 1) / a
    if first:
        tau = h / sigma
    else:
        root = sigma ** (1.0 / (1.0 - n)) if n > 1 else 1.0
        rho = min(1.0, 1.0 / b)
        tau = min(rho * root, sigma) if theta <= 0 else rho * min(root, 1.0 / theta)
    return (1.0 - theta) / sigma, tau
