"""pinnmpc: physics-informed neural networks as fast, differentiable models for NMPC of manipulators."""

from pinnmpc.surrogate import CheckpointError, Surrogate, load_surrogate
from pinnmpc.systems import load_system

__version__ = "0.1.0"
__all__ = ["CheckpointError", "Surrogate", "__version__", "load_surrogate", "load_system"]
