"""The model monitor's verdict (issue 63): real closed loops of the shipped planar3 network on the model and on the
MuJoCo `lab` robot, its level from the checkpoint or measured on the model, the headline and metrics.json."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from pinnmpc.simulation.model_fit import FIT_RATIO, LEVEL_FLOOR, measured_level, recorded_level
from pinnmpc.simulation.run import run_closed_loop
from pinnmpc.simulation.setup import build_controller
from pinnmpc.surrogate import load_surrogate
from pinnmpc.surrogate.checkpoint import shipped
from pinnmpc.systems import load_system
from tests.conftest import ROOT

pytest.importorskip("mujoco")

COMMON = ["system=planar3", "max_steps=30", "progress=false", "plots=false"]
VERDICT = "the model does not fit the robot"


def _loop(make_cfg: Any, run_dir: Path, *overrides: str) -> tuple[dict[str, Any], list[str]]:
    """One real closed loop and the headline it announced."""
    from pinnmpc.simulation.metrics import headline

    said: list[str] = []
    m = run_closed_loop(make_cfg("closed_loop", [*COMMON, *overrides]), run_dir, announce=lambda r: said.append(
        headline(r, run_dir)))  # fmt: skip
    return m, said


def test_on_the_model_the_network_fits_and_the_headline_is_quiet(make_cfg, tmp_path: Path) -> None:
    m, (line,) = _loop(make_cfg, tmp_path, "plant=mujoco")
    assert m["status"] == "ok" and m["model_fits"] is True and m["model_miss_ratio"] <= FIT_RATIO
    mon = m["model_monitor"]
    assert mon["level_source"] == "checkpoint" and mon["level"] == load_surrogate(shipped("planar3")).meta[
        "best_val_rmse_position"]  # fmt: skip
    assert VERDICT not in line and "model one-step miss p95" in line


def test_on_the_lab_robot_the_nominal_network_does_not_fit_and_says_what_to_do(make_cfg, tmp_path: Path) -> None:
    m, (line,) = _loop(make_cfg, tmp_path, "plant=mujoco", "plant.robot=lab")
    assert m["model_fits"] is False and m["model_miss_ratio"] > 10 * FIT_RATIO, m["model_miss_ratio"]
    assert f"{VERDICT}: its one-step miss is {m['model_miss_ratio']:.0f}x its own level" in line, line
    assert "fine-tune" in line and "identify" in line and "docs/robot.md" in line
    on_disk = json.loads((tmp_path / "metrics.json").read_text())
    assert on_disk["model_fits"] is False and on_disk["model_miss_ratio"] == pytest.approx(m["model_miss_ratio"])
    assert on_disk["model_monitor"]["worst"].startswith("q_")


def test_measurement_noise_is_not_taken_for_a_robot_that_is_not_the_model(make_cfg, tmp_path: Path) -> None:
    m, (line,) = _loop(make_cfg, tmp_path, "noise_sigma=1e-3")
    assert m["model_fits"] is True and m["model_monitor"]["expected"] > 1e-3 and VERDICT not in line


def test_a_checkpoint_without_a_recorded_level_is_measured_on_the_model(make_cfg, tmp_path: Path) -> None:
    net = load_surrogate(shipped("planar3"))
    recorded = net.meta["best_val_rmse_position"]
    net.meta = {}  # as a network saved without its training record
    bare = net.save(tmp_path / "bare.pt")
    m, _ = _loop(make_cfg, tmp_path / "run", f"checkpoint={bare}", "plant=mujoco")
    mon = m["model_monitor"]
    assert mon["level_source"] == "measured on the model" and 0.5 < mon["level"] / recorded < 2.0, mon
    assert m["model_fits"] is True
    # the true model's values (controller.model=exact_values): measured, not the network's record
    cfg = make_cfg("closed_loop", ["system=planar3", "controller.model=exact_values"])
    system = load_system("planar3")
    controller, _, _ = build_controller(cfg, system)
    assert recorded_level(controller) is None and measured_level(controller, system) < LEVEL_FLOOR


def test_the_command_line_headline_says_it(tmp_path: Path) -> None:
    cmd = [sys.executable, "-m", "pinnmpc.closed_loop", *COMMON, "plant=mujoco", "plant.robot=lab",
           f"hydra.run.dir={tmp_path}"]  # fmt: skip
    r = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    assert VERDICT in r.stdout.splitlines()[-1]
    assert json.loads((tmp_path / "metrics.json").read_text())["model_fits"] is False
