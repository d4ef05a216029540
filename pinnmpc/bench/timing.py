"""Where and how the bench measures: the machine, wall times of repeated calls and their summary."""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import scipy
import torch
from threadpoolctl import threadpool_info
from torch import Tensor

PERCENTILE = 95.0  # the "p95" of every table


def cpu_model() -> str:
    """CPU name for the machine line: platform.processor() is empty on most Linux systems."""
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.exists():
        for line in cpuinfo.read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or "unknown CPU"


def machine_info() -> dict[str, Any]:
    """Where the numbers were measured: timings mean nothing without the machine and library versions."""
    return {
        "platform": platform.platform(),
        "cpu": cpu_model(),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "torch_threads": torch.get_num_threads(),
        "blas_threads": [(i["internal_api"], i["num_threads"]) for i in threadpool_info()],
        "load_average_1min": float(os.getloadavg()[0]) if hasattr(os, "getloadavg") else float("nan"),
    }


def time_calls(fn: Callable[[int], object], repeats: int, warmup: int) -> np.ndarray:
    """Wall times of fn(i) after untimed warm-up calls; i lets a call pick its own input."""
    for i in range(warmup):
        fn(i)
    times = np.empty(int(repeats))
    for i in range(int(repeats)):
        start = time.perf_counter()
        fn(i)
        times[i] = time.perf_counter() - start
    return times


def timing_stats(times: np.ndarray) -> dict[str, float]:
    """Median, mean and p95: the mean alone hides the heavy tail of adaptive solvers."""
    return {
        "median_s": float(np.median(times)),
        "mean_s": float(np.mean(times)),
        "p95_s": float(np.percentile(times, PERCENTILE)),
    }


def as_numpy(y: Tensor | np.ndarray) -> np.ndarray:
    """float64 numpy copy of any method's output, so errors are computed the same way for all."""
    if isinstance(y, Tensor):
        return y.detach().to(torch.float64).numpy()
    return np.asarray(y, dtype=np.float64)
