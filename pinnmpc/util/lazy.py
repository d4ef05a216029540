"""Package attributes imported on first use, so that a command's --help or a refused setting does not wait for
torch: `__getattr__, __dir__ = lazy_exports(__name__, {"name": "module.defining.it"})` in the package's __init__."""

from __future__ import annotations

import sys
from collections.abc import Callable
from importlib import import_module
from typing import Any


def lazy_exports(package: str, where: dict[str, str]) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """A module __getattr__ that imports each name from its module when first asked for, and the __dir__ to go
    with it."""

    def attribute(name: str) -> Any:
        if name not in where:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(import_module(where[name]), name)
        setattr(sys.modules[package], name, value)  # asked once: a plain attribute from then on
        return value

    def names() -> list[str]:
        return sorted({*vars(sys.modules[package]), *where})

    return attribute, names
