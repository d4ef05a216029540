"""CasADi functions compiled to C once and cached, and a torch autograd bridge to them.

A rigid-body right-hand side built symbolically (adam's CasADi backend) and compiled with the system's C
compiler evaluates a whole batch of collocation points, and its vector-Jacobian product, far cheaper than the
same algorithm as many small torch operations; training uses it through `CasadiRhs`.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np
import torch
from torch import Tensor

from pinnmpc.systems.cache import CACHE_ENV as CACHE_ENV  # re-exported: where compiled functions are kept
from pinnmpc.systems.cache import CompileError, library
from pinnmpc.systems.cache import cache_dir as cache_dir


def compile_functions(name: str, functions: list[ca.Function], opt: str = "-O1") -> dict[str, ca.Function]:
    """Generate C for the functions, compile it once (cached by source hash, checked before it is loaded, rebuilt
    when bad: pinnmpc.systems.cache) and load each as an external.

    opt: the C compiler's optimisation flag; lower levels compile large generated files (a 7-joint arm) sooner
    and run a little slower (docs/results.md, panda)."""
    gen = ca.CodeGenerator(f"{name}.c", {"with_header": False})
    for f in functions:
        gen.add(f)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            gen.generate(f"{tmp}/")
            source = (Path(tmp) / f"{name}.c").read_text()
    except (OSError, RuntimeError) as e:
        said = str(e).strip().splitlines()
        raise CompileError(f"generating C for {name} failed: {said[-1] if said else type(e).__name__}") from None
    lib = library(name, source, opt)
    try:
        return {f.name(): ca.external(f.name(), str(lib)) for f in functions}
    except RuntimeError as e:
        said = str(e).strip().splitlines()
        raise CompileError(f"loading {lib} failed: {said[-1] if said else type(e).__name__}") from None


ROWS_PER_THREAD = 512  # a batch is split over threads only in chunks at least this big (a thread's start costs
#   about what a few hundred rows of a small arm's rhs do): controller calls stay serial, training batches go parallel


def batch_threads(n: int) -> int:
    """Threads for a batch of n rows: torch's thread count (the `threads` setting), fewer for a small batch; the
    rows are independent, so the result is bit-identical to a serial call."""
    return max(1, min(torch.get_num_threads(), n // ROWS_PER_THREAD))


class BatchedFunction:
    """A compiled CasADi function over rows of numpy arrays via CasADi's buffer API: no DM conversions or transposes
    (at batch 1 a Python-level call's overhead would be most of a controller step; at training size the
    conversions a sizeable share of the rhs). Large batches run on torch's threads (`batch_threads`)."""

    def __init__(self, f: ca.Function) -> None:
        sparse = [j for j in range(f.n_out()) if not f.sparsity_out(j).is_dense()]
        if sparse:  # the buffer holds only the nonzeros, in CasADi's order: read as dense rows they are garbage
            raise ValueError(f"{f.name()}: outputs {sparse} are sparse; expected dense outputs (ca.densify them)")
        self.f = f
        self.sizes = [f.numel_out(j) for j in range(f.n_out())]
        self._calls: dict[tuple[int, int], tuple[ca.Function, Any, Any]] = {}  # per (rows, threads): function,
        #   buffer, evaluator

    def __call__(self, *args: np.ndarray) -> list[np.ndarray]:
        """Inputs (B, n_i) each; outputs (B, m_j) each. Rows are samples: a C-ordered (B, n) array is the
        column-major (n, B) matrix the mapped function takes, so nothing is transposed."""
        n = args[0].shape[0]
        if n == 0:  # CasADi cannot map over no rows
            return [np.zeros((0, self.f.size1_out(j) * self.f.size2_out(j))) for j in range(self.f.n_out())]
        threads = batch_threads(n)
        call = self._calls.get((n, threads))
        if call is None:
            fm = self.f if n == 1 else self.f.map(n, "serial") if threads == 1 else self.f.map(n, "thread", threads)
            call = self._calls[n, threads] = (fm, *fm.buffer())
        _, buf, evaluate = call
        args = [np.ascontiguousarray(a, dtype=np.float64) for a in args]
        outs = [np.empty((n, m)) for m in self.sizes]
        for i, a in enumerate(args):
            buf.set_arg(i, memoryview(a))
        for j, o in enumerate(outs):
            buf.set_res(j, memoryview(o))
        evaluate()
        return outs


class CompiledRhs:
    """dx/dt = f(x, u) and its vector-Jacobian product, compiled; numpy in and out, batched over rows."""

    def __init__(self, name: str, f: ca.Function) -> None:
        x, u = ca.SX.sym("x", f.size1_in(0)), ca.SX.sym("u", f.size1_in(1))
        y, ybar = f(x, u), ca.SX.sym("ybar", f.size1_out(0))
        outputs = [ca.jtimes(y, x, ybar, True), ca.jtimes(y, u, ybar, True)]  # x-bar, u-bar = J^T ybar
        vjp = ca.Function(f"{name}_vjp", [x, u, ybar], [ca.densify(o) for o in outputs], {"cse": True})
        fwd = ca.Function(f"{name}_rhs", [x, u], [ca.densify(y)], {"cse": True})
        lib = compile_functions(name, [fwd, vjp])
        self.rhs = BatchedFunction(lib[f"{name}_rhs"])
        self.vjp = BatchedFunction(lib[f"{name}_vjp"])


class CasadiRhs(torch.autograd.Function):
    """torch autograd bridge: forward through the compiled rhs, backward through its compiled VJP."""

    @staticmethod
    def forward(ctx, x: Tensor, u: Tensor, compiled: CompiledRhs) -> Tensor:
        """dx/dt for x (B, nx), u (B, nu) in x's dtype and on its device (the C code runs on the CPU)."""
        ctx.compiled = compiled
        ctx.save_for_backward(x, u)
        (y,) = compiled.rhs(x.detach().cpu().double().numpy(), u.detach().cpu().double().numpy())
        return torch.from_numpy(y).to(device=x.device, dtype=x.dtype)

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor | None, Tensor | None, None]:
        """x-bar, u-bar from the compiled VJP."""
        x, u = ctx.saved_tensors
        gx, gu = ctx.compiled.vjp(*(a.detach().cpu().double().numpy() for a in (x, u, grad)))
        return torch.from_numpy(gx).to(x.device, x.dtype), torch.from_numpy(gu).to(u.device, u.dtype), None
