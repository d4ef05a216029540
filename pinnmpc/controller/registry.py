"""Controller kinds by name (`controller.kind`): a kind is a controller class, its settings and one registration.

The settings are a dataclass subclassing ControllerSettings (controller/base.py): each field with its default, check
and docstring. A builder takes the kind's checked settings, the job's whole config (checkpoint, ...) and the system,
and returns the controller, the state box its model is valid in (None: everywhere) and its control period. The
built-in kinds (`pinn`: the network NMPC of nmpc.yaml and exact.yaml; `casadi`: the classical NMPC of casadi.yaml)
register in pinnmpc.simulation.setup; a new kind registers the same way, from anywhere, before the job runs:

    @register_controller("mine", MySettings)
    def build_mine(settings, cfg, system): return MyController(settings), None, system.tau
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from pinnmpc.controller.base import Controller, ControllerSettings, checked_settings
from pinnmpc.systems.base import Box, System
from pinnmpc.systems.settings import system_dims
from pinnmpc.util.checks import SettingError

Built = tuple[Controller, Box | None, float]  # the controller, where its model is valid, its control period
Builder = Callable[[Any, Any, System], Built]  # (its checked settings, the job's config, the system) -> Built

_KINDS: dict[str, tuple[Builder, type[ControllerSettings]]] = {}


def register_controller(kind: str, settings: type[ControllerSettings]) -> Callable[[Builder], Builder]:
    """Decorator: `controller.kind=<kind>` builds with the decorated function from `settings` (a kind registered
    twice is refused, so two modules cannot silently replace each other's controller)."""
    if not isinstance(kind, str) or not kind.isidentifier():
        raise ValueError(f"controller kind {kind!r}: expected a name (letters, digits, underscores)")
    if not (isinstance(settings, type) and issubclass(settings, ControllerSettings)):
        raise ValueError(f"controller kind {kind!r}: settings {settings!r}; expected a ControllerSettings subclass")

    def register(builder: Builder) -> Builder:
        """Record the builder and its settings under the kind."""
        if kind in _KINDS and _KINDS[kind][0] is not builder:
            raise ValueError(f"controller kind {kind!r} is registered already (by {_KINDS[kind][0].__module__})")
        _KINDS[kind] = (builder, settings)
        return builder

    return register


def unregister_controller(kind: str) -> None:
    """Forget a kind (a test's own, or a plugin being unloaded)."""
    _KINDS.pop(kind, None)


def controller_kinds() -> list[str]:
    """The registered kinds, in registration order."""
    return list(_KINDS)


def _entry(kind: str) -> tuple[Builder, type[ControllerSettings]]:
    """A registered kind's builder and settings, or one line naming the kinds there are."""
    if kind not in _KINDS:
        raise SettingError(f"controller.kind={kind!r}; expected one of {', '.join(repr(k) for k in _KINDS)}")
    return _KINDS[kind]


def settings_class(kind: str) -> type[ControllerSettings]:
    """The settings dataclass of a registered kind."""
    return _entry(kind)[1]


def kind_of(controller: Any) -> str:
    """The kind a controller config names (`controller.kind`; absent: pinn, the network NMPC)."""
    return str(controller.get("kind", "pinn")) if hasattr(controller, "get") else str(controller.kind)


def controller_settings(controller: Any, system: System) -> ControllerSettings:
    """The checked settings of a controller config (its kind's dataclass) for the system: one line naming the key
    of a bad value, a misspelt or a missing one."""
    return checked_settings(settings_class(kind_of(controller)), controller, system_dims(system))


def build_registered(cfg: Any, system: System) -> Built:
    """The controller of the registered kind that the job's `controller` names, from its checked settings."""
    builder, _ = _entry(kind_of(cfg.controller))
    return builder(controller_settings(cfg.controller, system), cfg, system)


def register_configs() -> None:
    """Each registered kind's settings as a structured config (group schema/controller, by kind): the base of
    conf/controller/<name>.yaml."""
    from hydra.core.config_store import ConfigStore

    store = ConfigStore.instance()
    for kind, (_, settings) in _KINDS.items():
        store.store(group="schema/controller", name=kind, node=settings)
