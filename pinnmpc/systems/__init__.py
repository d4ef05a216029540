"""Controlled systems: a small protocol, the PowerCube's closed form and URDF arms, found by name."""

from pinnmpc.systems.base import Box, System, check_shapes
from pinnmpc.systems.powercube import PowerCube, PowerCubeParams
from pinnmpc.systems.registry import available, build_system, load_system, system_config
from pinnmpc.systems.urdf import RigidArm

__all__ = [
    "Box",
    "PowerCube",
    "PowerCubeParams",
    "RigidArm",
    "System",
    "available",
    "build_system",
    "check_shapes",
    "load_system",
    "system_config",
]
