"""Hydra's structured configs of pinnmpc: the dataclasses whose fields, types, defaults and field docstrings are
the settings of the controller kinds (controller), the solvers (controller.solvers.<name>), the plant (plant) and
the training (module, data).
The commands register them before they compose; call register_configs() before a hydra.compose of your own."""

from __future__ import annotations


def register_configs() -> None:
    """Put every structured config into Hydra's ConfigStore (idempotent)."""
    import pinnmpc.simulation.setup  # noqa: F401  (registers the built-in controller kinds)
    from pinnmpc.controller.registry import register_configs as controllers
    from pinnmpc.controller.solvers import register_configs as solvers
    from pinnmpc.plant.settings import register_configs as plants
    from pinnmpc.training.settings import register_configs as training

    controllers()
    solvers()
    plants()
    training()
