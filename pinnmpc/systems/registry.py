"""Systems by name: conf/system/<name>.yaml is the one description of a robot, read here and by Hydra alike."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from pinnmpc.systems.base import System

SYSTEM_CONF = Path(__file__).resolve().parents[2] / "conf" / "system"  # the configs next to the package


def available() -> list[str]:
    """Names of the systems with a config."""
    return sorted(p.stem for p in SYSTEM_CONF.glob("*.yaml"))


def system_config(name: str | Path) -> DictConfig:
    """conf/system/<name>.yaml, or a system .yaml by path (a user's own arm outside the package)."""
    own = Path(name).expanduser()
    if own.suffix in (".yaml", ".yml"):
        if not own.is_file():
            raise ValueError(f"system={str(name)!r}: no such file; expected a system .yaml or one of {available()}")
        return OmegaConf.load(own)
    path = SYSTEM_CONF / f"{name}.yaml"
    if not path.is_file():
        raise ValueError(f"system={str(name)!r}: no {path}; expected one of {available()} or a path to a .yaml")
    return OmegaConf.load(path)


def build_system(cfg: Any) -> System:
    """The System of a composed `system` config node (its `dynamics` part); a description the system refuses
    raises its own one-line error, not Hydra's wrapper around it."""
    node = cfg.dynamics if "dynamics" in cfg else cfg
    try:
        return instantiate(node)
    except InstantiationException as e:
        if isinstance(e.__cause__, (ValueError, FileNotFoundError)):
            raise e.__cause__ from None
        raise


def load_system(name: str | Path = "powercube") -> System:
    """A controlled arm by name (conf/system) or by the path of its .yaml: rhs(x, u) batched and differentiable in
    torch, state/input names, tau. The config's per-joint lists are checked against the arm here too, so a
    wrong-length list shows when the arm loads, not in a closed loop after a training."""
    from pinnmpc.systems.settings import validate_system

    cfg = system_config(name)
    system = build_system(cfg)
    validate_system(OmegaConf.create({"system": cfg}), system)
    return system
