"""One knob for CPU threads: torch, the BLAS under numpy/scipy and the compiled rhs's batches alike."""

from __future__ import annotations

import os
from numbers import Integral

import torch
from threadpoolctl import threadpool_limits


def available_cores() -> int:
    """Cores this process may run on (its affinity mask, as a container or `taskset` sets it)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def use_threads(n: int) -> None:
    """Small controller solves are fastest single-threaded: threaded BLAS adds overhead to each tiny GEMM.
    0 takes every available core (a GPU host, whose CPU evaluates a URDF arm's rhs in training)."""
    if isinstance(n, bool) or not isinstance(n, Integral) or n < 0:
        raise ValueError(f"threads={n!r}; expected a whole number >= 1, or 0 for every available core")
    n = int(n) or available_cores()
    torch.set_num_threads(n)
    threadpool_limits(limits=n)  # stays in force for the process
