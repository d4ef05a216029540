"""The learned flow map: network, frozen-arm prior, staged networks, numpy evaluation and the checkpoint format."""

from pinnmpc.surrogate.checkpoint import (
    FORMAT,
    FORMAT_VERSION,
    SHIPPED,
    CheckpointError,
    Surrogate,
    load_surrogate,
    shipped,
)

__all__ = ["FORMAT", "FORMAT_VERSION", "SHIPPED", "CheckpointError", "Surrogate", "load_surrogate", "shipped"]
