"""Systems by name: conf/system/<name>.yaml is the one description of a robot, read here and by Hydra alike."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from pinnmpc.systems.base import System

SYSTEM_CONF = Path(__file__).resolve().parents[2] / "conf" / "system"  # the configs next to the package


def available() -> list[str]:
    """Names of the systems with a config."""
    return sorted(p.stem for p in SYSTEM_CONF.glob("*.yaml"))


def system_config(name: str) -> DictConfig:
    """conf/system/<name>.yaml, interpolations resolved within it."""
    path = SYSTEM_CONF / f"{name}.yaml"
    if not path.is_file():
        raise ValueError(f"system={name!r}: no {path}; expected one of {available()}")
    return OmegaConf.load(path)


def build_system(cfg: Any) -> System:
    """The System of a composed `system` config node (its `dynamics` part)."""
    node = cfg.dynamics if "dynamics" in cfg else cfg
    return instantiate(node)


def load_system(name: str = "powercube") -> System:
    """A controlled arm by name: rhs(x, u) batched and differentiable in torch, state/input names, tau."""
    return build_system(system_config(name))
