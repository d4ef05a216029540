"""Controller kinds by name (`controller.kind`): a kind is a builder and one registration.

A builder takes the job's whole config (the controller's settings are `cfg.controller`) and the system, and returns
the controller, the state box its model is valid in (None: everywhere) and its control period. The built-in kinds
(`pinn`: the network NMPC of nmpc.yaml and exact.yaml; `casadi`: the classical NMPC) register in
pinnmpc.simulation.setup; a new kind registers the same way, from anywhere, before the job runs:

    @register_controller("mine")
    def build_mine(cfg, system): return MyController(...), None, system.tau
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from pinnmpc.controller.nmpc import Controller
from pinnmpc.systems.base import Box, System

Built = tuple[Controller, Box | None, float]  # the controller, where its model is valid, its control period
Builder = Callable[[Any, System], Built]

_KINDS: dict[str, Builder] = {}


def register_controller(kind: str) -> Callable[[Builder], Builder]:
    """Decorator: `controller.kind=<kind>` builds with the decorated function (a kind registered twice is refused,
    so two modules cannot silently replace each other's controller)."""
    if not isinstance(kind, str) or not kind.isidentifier():
        raise ValueError(f"controller kind {kind!r}: expected a name (letters, digits, underscores)")

    def register(builder: Builder) -> Builder:
        """Record the builder under its kind."""
        if kind in _KINDS and _KINDS[kind] is not builder:
            raise ValueError(f"controller kind {kind!r} is registered already (by {_KINDS[kind].__module__})")
        _KINDS[kind] = builder
        return builder

    return register


def unregister_controller(kind: str) -> None:
    """Forget a kind (a test's own, or a plugin being unloaded)."""
    _KINDS.pop(kind, None)


def controller_kinds() -> list[str]:
    """The registered kinds, in registration order."""
    return list(_KINDS)


def build_registered(kind: str, cfg: Any, system: System) -> Built:
    """The controller of a registered kind, or one line naming the kinds there are."""
    if kind not in _KINDS:
        raise ValueError(f"controller.kind={kind!r}; expected one of {', '.join(repr(k) for k in _KINDS)}")
    return _KINDS[kind](cfg, system)
