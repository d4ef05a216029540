"""One knob for CPU threads: torch and the BLAS under numpy/scipy alike."""

from __future__ import annotations

import torch
from threadpoolctl import threadpool_limits


def use_threads(n: int) -> None:
    """Small controller solves are fastest single-threaded: threaded BLAS adds overhead to each tiny GEMM."""
    if int(n) < 1:
        raise ValueError(f"threads must be >= 1, got {n}")
    torch.set_num_threads(int(n))
    threadpool_limits(limits=int(n))  # stays in force for the process
