"""pinnmpc: physics-informed neural networks as fast, differentiable models for NMPC of manipulators."""

import os

# torch's OpenMP threads spin-wait for each other between parallel regions; when another process holds one of the
# cores, the spinning thread waits on a descheduled one through every small operation and multi-threaded training
# crawls (docs/training.md, "Threads"). A short spin keeps the speed on an idle machine and bounds that loss. It
# must be set before torch loads OpenMP, so here; it is only a default: set GOMP_SPINCOUNT yourself to override.
os.environ.setdefault("GOMP_SPINCOUNT", "10000")

from pinnmpc.util.lazy import lazy_exports  # noqa: E402 (after the OpenMP default)

__version__ = "0.1.0"
__all__ = ["CheckpointError", "Surrogate", "__version__", "load_surrogate", "load_system"]
__getattr__, __dir__ = lazy_exports(  # imported on first use: a command's --help does not wait for torch
    __name__,
    {
        "CheckpointError": "pinnmpc.surrogate.checkpoint",
        "Surrogate": "pinnmpc.surrogate.checkpoint",
        "load_surrogate": "pinnmpc.surrogate.checkpoint",
        "load_system": "pinnmpc.systems",
    },
)
