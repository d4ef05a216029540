"""The paper's self-loop test and the robustness grid, run for real on small sizes."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pinnmpc.simulation.robustness import run_robustness
from pinnmpc.simulation.self_loop import run_self_loop, sine_inputs


def test_sine_inputs_are_the_papers():
    u = sine_inputs(20, [0.5, -0.5])
    assert u.shape == (20, 2)
    assert np.allclose(u[:, 0], 0.5 * np.sin(np.linspace(0, 2 * np.pi, 20)))
    assert np.allclose(u[:, 1], -u[:, 0])
    assert sine_inputs(5, [20.0, -8.0, 2.0]).shape == (5, 3)  # one amplitude per input, any nu
    with pytest.raises(ValueError, match="amplitude"):
        sine_inputs(5, [float("nan")])


def test_self_loop_against_plant(make_cfg, tmp_path):
    m = run_self_loop(make_cfg("self_loop", ["steps=8"]), tmp_path)
    data = np.load(tmp_path / "self_loop.npz")
    assert data["x_pinn"].shape == data["x_plant"].shape == (9, 4)
    assert np.array_equal(data["x_pinn"][0], data["x_plant"][0])
    assert 0 < m["mae"]["alpha"] < 0.05 and 0 < m["mae"]["beta"] < 0.05
    assert json.loads((tmp_path / "metrics.json").read_text())["steps"] == 8
    assert (tmp_path / "self_loop.png").stat().st_size > 10_000


def test_robustness_grid_writes_one_row_per_setting(make_cfg, tmp_path):
    cfg = make_cfg(
        "robustness",
        ["reference.path=null", "max_steps=8", "robustness.noise_sigma=[0.0,0.003]", "robustness.friction_scale=[1.2]"],
    )
    rows = run_robustness(cfg, tmp_path)
    assert [(r["noise_sigma"], r["friction_scale"]) for r in rows] == [(0.0, 1.2), (0.003, 1.2)]
    assert all(r["status"] == "ok" and r["bounded"] for r in rows)
    assert rows[0]["mae"] != rows[1]["mae"]  # the noise reached the controller
    assert "| 0.003 | 1.2 |" in (tmp_path / "robustness.md").read_text()
    assert len(json.loads((tmp_path / "robustness.json").read_text())) == 2
