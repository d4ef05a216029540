"""python -m pinnmpc.time_basis: how well the time gates span the true flow, and which relaxation times help."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pinnmpc.systems.registry import build_system
from pinnmpc.time_basis import _summary
from pinnmpc.training.time_basis import basis_report, run_time_basis
from pinnmpc.util.checks import SettingError


def test_the_servo_fast_mode_is_what_the_panda_gates_miss(make_cfg) -> None:
    cfg = make_cfg("time_basis", ["system=panda"])
    arm = build_system(cfg.system)
    report = basis_report(arm, list(cfg.time_basis), [0.001, 0.005], 2, 1, arm.tau, cfg.t_max, 48, 1e-4, 1e-4, 0)
    before, after = np.array(report["basis"]["rms"]), np.array(report["greedy"][-1]["rms"])
    assert report["greedy"][-1]["time_basis"][:3] == list(cfg.time_basis)
    assert sorted(report["greedy"][-1]["time_basis"][3:]) == [0.001, 0.005]
    # K^-1 M reaches down to ~1 ms: with gates at 1 and 5 ms the velocity flow is nearly in their span
    assert np.all(after[7:] < before[7:] / 30) and before[7:].max() > 1e-3
    single = {entry["added"]: np.array(entry["rms"]) for entry in report["single"]}
    assert np.all(single[0.001] <= before * (1 + 1e-9))  # a bigger span never fits worse


def test_entry_point_writes_json_and_figure_and_refuses_bad_input(make_cfg, tmp_path) -> None:
    m = run_time_basis(make_cfg("time_basis", ["points=40", "dt=1e-3", "greedy=1"]), tmp_path)
    saved = json.loads((tmp_path / "time_basis.json").read_text())
    assert saved["basis"]["rms"] == m["basis"]["rms"] and len(m["basis"]["rms"]) == 4
    assert len(m["single"]) == 7 and len(m["greedy"]) == 1  # the default candidates but 0.02, a gate already
    assert (tmp_path / "time_basis.png").stat().st_size > 10_000
    # the closing lines weigh the misfit against the system's one-step targets
    assert m["targets"] == [1e-3, 1e-3, 1e-2, 1e-2] and m["near_target"] == 0.5
    near = [n for n, v, t in zip(m["state_names"], m["basis"]["rms"], m["targets"]) if v > 0.5 * t]
    assert all(f"{n} " in _summary(m, tmp_path).split("target: ")[-1] for n in near)  # named, with their numbers
    assert "every state's misfit is below 100x its one-step" in _summary({**m, "near_target": 100.0}, tmp_path)
    slow = run_time_basis(
        make_cfg("time_basis", ["points=40", "dt=1e-3", "greedy=0", "time_basis=[0.5]"]), tmp_path / "s"
    )
    assert "above 0.5x the one-step target: alpha" in _summary(slow, tmp_path) and "line above" not in _summary(
        slow, tmp_path
    )
    no_targets = run_time_basis(
        make_cfg("time_basis", ["points=40", "dt=1e-3", "greedy=0", "system.targets=null"]), tmp_path / "n"
    )
    assert no_targets["targets"] is None and "one-step target" not in _summary(no_targets, tmp_path)
    with pytest.raises(SettingError, match=r"time_basis=\[-0.01\]"):
        run_time_basis(make_cfg("time_basis", ["time_basis=[-0.01]"]), tmp_path / "bad")
    with pytest.raises(SettingError, match="t_max=0.1 is below the system's tau=0.2"):
        run_time_basis(make_cfg("time_basis", ["t_max=0.1"]), tmp_path / "bad2")
