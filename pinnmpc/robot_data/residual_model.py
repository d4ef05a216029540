"""The model a fine-tuning's physics residual weighs: the nominal arm's, or one identified from the robot's logs.

A network fine-tuned on logs keeps the physics residual as a regulariser where the logs do not reach. Of the nominal
model that residual pulls towards an arm the robot is not; of a model `python -m pinnmpc.identify` fitted to the same
logs (payload, armature, friction) it pulls towards the robot as far as the model's structure can hold it, and the
network learns the rest (dry friction's stick, what no coefficient covers) from the logs themselves. A network with a
frozen-arm prior gets that model's frozen arm as its prior too, so its output starts at the robot's linear response,
not the nominal arm's.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import OmegaConf

from pinnmpc.systems.base import System
from pinnmpc.systems.registry import load_system, system_config
from pinnmpc.systems.urdf_files import portable_urdf

COEFFICIENTS = ("viscous", "coulomb", "servo_gain", "payload", "armature")  # what a fit can change: kept in the meta


def physics_model(
    path: str | None, system: System, prior_slope: float | None = None
) -> tuple[System, dict[str, Any] | None, dict[str, Any] | None]:
    """The system whose residual the physics loss uses, what to record of it and its description for a frozen-arm
    prior, whose dry friction gets `prior_slope` (None: the model's own; None, None: the arm's own): `path` is a
    system config written by pinnmpc.identify for this arm; another arm's, another period or box is refused."""
    if not path:
        return system, None, None
    file = Path(path).expanduser()
    if file.suffix not in (".yaml", ".yml") or not file.is_file():
        raise ValueError(f"physics={path}: no such file; expected a system .yaml written by pinnmpc.identify")
    config = OmegaConf.to_container(system_config(file), resolve=True)
    origin = config.get("identified_from") or {}
    if origin.get("system") != system.name:
        raise ValueError(
            f"physics={path}: identified from {origin.get('system')!r}; expected a model of {system.name!r} "
            f"(python -m pinnmpc.identify system={system.name} logs=[...] out={file.name})"
        )
    model = load_system(file)
    same = (
        model.tau == system.tau
        and list(model.state_names) == list(system.state_names)
        and all(np.allclose(getattr(model, b).low, getattr(system, b).low) for b in ("state_box", "input_box"))
        and all(np.allclose(getattr(model, b).high, getattr(system, b).high) for b in ("state_box", "input_box"))
    )
    if not same:
        raise ValueError(
            f"physics={path}: its tau, state names or boxes differ from {system.name}'s; expected the same arm "
            "(only its coefficients fitted)"
        )
    fitted = {k: config["dynamics"].get(k) for k in COEFFICIENTS if config["dynamics"].get(k) is not None}
    record = {"file": str(file), "name": model.name, "coefficients": fitted}
    record.update({k: v for k, v in origin.items() if k != "system"})
    description = dict(config["dynamics"])
    servo = getattr(model, "actuation", None) == "velocity_servo"
    if prior_slope is not None and getattr(model, "coulomb", None) and any(model.coulomb):
        # dry friction in a frozen-arm prior (a servo's settled, any arm's with frozen_arm_friction): smoother there
        # than in the model, or (0) not at all, the network learning it from the logs
        if prior_slope > 0:
            description["coulomb_slope"] = float(prior_slope)
        elif servo:
            description.pop("coulomb")
        else:  # a torque arm's coulomb is required: zeros
            description["coulomb"] = [0.0] * len(model.coulomb)
        record["prior_coulomb_slope"] = float(prior_slope)
    if getattr(model, "urdf", None):  # the file the arm was built from, found wherever the network is loaded
        description["urdf"] = portable_urdf(model.urdf)
    return model, {"identified_from": system.name, **record}, description
