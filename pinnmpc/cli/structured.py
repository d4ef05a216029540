"""Hydra's structured configs of pinnmpc: the dataclasses whose fields, types, defaults and field docstrings are
the settings of the solvers (controller.solvers.<name>), of the plant (plant) and of the training (module, data).
The commands register them before they compose; call register_configs() before a hydra.compose of your own."""

from __future__ import annotations


def register_configs() -> None:
    """Put every structured config into Hydra's ConfigStore (idempotent)."""
    from pinnmpc.controller.solvers import register_configs as solvers
    from pinnmpc.plant.settings import register_configs as plants
    from pinnmpc.training.settings import register_configs as training

    solvers()
    plants()
    training()
