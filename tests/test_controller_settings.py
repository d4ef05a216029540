"""One settings dataclass per controller kind: each option has one default, whether the caller enters by the CLI
(conf/controller/*.yaml composed on the dataclass), by Python (a dict or the dataclass) or by a test; a misspelt
or bad key is one line naming it, for every kind."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path
from typing import Any

import pytest
import yaml
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from pinnmpc.cli.structured import register_configs
from pinnmpc.controller.base import ControllerSettings
from pinnmpc.controller.build import build_nmpc
from pinnmpc.controller.classical.settings import ClassicalSettings
from pinnmpc.controller.registry import controller_kinds, controller_settings, settings_class
from pinnmpc.controller.settings import NetworkSettings
from pinnmpc.surrogate.checkpoint import load_surrogate
from pinnmpc.surrogate.network import PINN
from pinnmpc.systems import load_system

CONF = Path(__file__).resolve().parents[1] / "conf"
FALLBACK = re.compile(r"^\$\{oc\.select:[\w.]+,(.*)\}$")  # ${oc.select:system...,<the value without the arm's>}


def _fallbacks(node: Any, prefix: str = "") -> dict[str, Any]:
    """Every `${oc.select:<system key>,<fallback>}` of a controller yaml, by its dotted key, fallback parsed."""
    out: dict[str, Any] = {}
    for key, value in (node or {}).items():
        if isinstance(value, dict):
            out.update(_fallbacks(value, f"{prefix}{key}."))
        elif isinstance(value, str) and (m := FALLBACK.match(value)):
            out[f"{prefix}{key}"] = yaml.safe_load(m.group(1))
    return out


def _default(cls: type, dotted: str) -> Any:
    """A (nested) field's default in a settings dataclass."""
    obj = cls(Q=[], R=[])
    for part in dotted.split("."):
        obj = getattr(obj, part)
    return obj


@pytest.mark.parametrize("name, cls", [("casadi", ClassicalSettings), ("nmpc", NetworkSettings)])
def test_a_yaml_fallback_is_the_dataclass_default(name: str, cls: type) -> None:
    """Where a controller yaml takes the arm's value, its fallback for an arm without one is the field's default."""
    text = yaml.safe_load((CONF / "controller" / f"{name}.yaml").read_text())
    fallbacks = _fallbacks(text)
    assert fallbacks, f"{name}.yaml names no arm-dependent setting"
    for key, fallback in fallbacks.items():
        assert fallback == _default(cls, key), f"{name}.yaml {key}: fallback {fallback!r} vs default"


@pytest.mark.parametrize("config", ["nmpc", "casadi", "exact"])
def test_the_cli_composes_each_kind_on_its_dataclass(config: str) -> None:
    """Every option not taken from the arm composes to its dataclass default; the arm's own ones to the arm's."""
    register_configs()
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("closed_loop", overrides=["system=planar3", f"controller={config}"])
    OmegaConf.resolve(cfg)
    settings = controller_settings(cfg.controller, load_system("planar3"))
    cls = settings_class(settings.kind)
    assert type(settings) is cls and list(cfg.system.control.Q) == settings.Q
    arm = {"Q", "R", "R_rate", "R_rate_previous_input", "joint_limits", "disturbance", "rti_trust", "coulomb_width"}
    arm |= {"model", "solvers"}
    arm |= set(_fallbacks(yaml.safe_load((CONF / "controller" / f"{config}.yaml").read_text())))
    for f in dataclasses.fields(cls):
        if f.name not in arm:
            assert getattr(settings, f.name) == _default(cls, f.name), f"controller.{f.name}"


def test_a_python_caller_gets_the_cli_defaults() -> None:
    """build_nmpc with a minimal dict: the offset-free gain, solver and horizon as `python -m pinnmpc.closed_loop`."""
    register_configs()
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("closed_loop", overrides=["system=planar3"])
    surrogate = load_surrogate(system="planar3")
    cli = build_nmpc(cfg.controller, surrogate).describe()
    python = build_nmpc({"Q": [1.0] * 6, "R": [1e-4] * 3}, surrogate).describe()
    for key in ("disturbance_gain", "solver", "real_time"):
        assert python[key] == cli[key], key
    assert python["disturbance_gain"] == 0.7 == NetworkSettings(Q=[], R=[]).disturbance.gain


def test_the_network_defaults_are_the_model_config() -> None:
    """PINN()'s keyword defaults are conf/model/pinn.yaml's where they need no system."""
    model = yaml.safe_load((CONF / "model" / "pinn.yaml").read_text())
    net = PINN([-1.0, -1.0], [1.0, 1.0], [-1.0], [1.0], t_max=0.1)
    assert net.config["activation"] == model["activation"] and list(net.config["hidden"]) == model["hidden"]


@pytest.mark.parametrize(
    "cls, key, value, expected",
    [
        (ClassicalSettings, "qpsoll", "hpipm", r"controller.qpsoll: not a setting here; expected one of \[.*'qpsol'"),
        (ClassicalSettings, "transcription", "euler", r"controller.transcription='euler': expected one of rk4, radau"),
        (ClassicalSettings, "rti_limit_steps", -1, r"controller.rti_limit_steps=-1: expected a whole number >= 0"),
        (NetworkSettings, "solver", "adam", r"controller.solver='adam': expected one of .*lifted_gauss_newton"),
        (NetworkSettings, "disturbance", {"gain": 1.5}, r"controller.disturbance.gain=1.5: expected a finite number"),
        (NetworkSettings, "disturbance", {"gian": 0.5}, r"controller.disturbance.gian: not a setting here"),
        (NetworkSettings, "Q", [1.0, 2.0], r"controller.Q=\[1.0, 2.0\]: expected 6 finite numbers >= 0"),
    ],
)
def test_a_bad_key_of_any_kind_is_one_line(cls: type, key: str, value: Any, expected: str) -> None:
    values = {"kind": cls(Q=[], R=[]).kind, "Q": [1.0] * 6, "R": [1e-4] * 3, key: value}
    with pytest.raises(ValueError, match=expected) as err:
        controller_settings(values, load_system("planar3"))
    assert "\n" not in str(err.value)


def test_every_builtin_kind_registers_its_settings() -> None:
    register_configs()
    assert controller_kinds()[:2] == ["pinn", "casadi"]
    assert all(issubclass(settings_class(k), ControllerSettings) for k in controller_kinds())
