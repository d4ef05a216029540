"""Controlled systems: a small protocol and its implementations."""

from pinnmpc.systems.base import Box, System, check_shapes
from pinnmpc.systems.powercube import PowerCube, PowerCubeParams

__all__ = ["Box", "PowerCube", "PowerCubeParams", "System", "check_shapes"]
