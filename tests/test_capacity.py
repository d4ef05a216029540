"""python -m pinnmpc.capacity: the configured network fitted directly to true one-step results."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pinnmpc import load_surrogate, load_system
from pinnmpc.training.capacity import one_step_data, run_capacity
from pinnmpc.util.checks import SettingError

TINY = ["points=256", "val_points=64", "max_steps=4", "model.hidden=[16,16]", "model.auto_scale.samples=64"]


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_a_direct_fit_learns_the_map_and_writes_its_report(make_cfg, tmp_path, dtype: str) -> None:
    sums = "system.network.angle_sums=[[0,1],[0,1,2],[1,2]]"  # the planar arm's absolute and relative link angles
    plain = "system.network.prior=null"  # the network alone (the prior has tests/test_prior.py)
    m = run_capacity(make_cfg("capacity", ["system=planar3", sums, plain, f"dtype={dtype}", *TINY]), tmp_path)
    assert m["steps"] == 4 and m["model"]["angle_sums"] == [[0, 1], [0, 1, 2], [1, 2]]
    assert np.all(np.array(m["val_rmse"]) < 0.7 * np.array(m["initial_val_rmse"]))  # it learned every state
    assert len(m["val_rmse"]) == 6 and m["targets"] == [1e-3, 1e-3, 1e-3, 1e-2, 1e-2, 1e-2]
    assert json.loads((tmp_path / "capacity.json").read_text())["val_rmse"] == m["val_rmse"]
    assert (tmp_path / "capacity.png").stat().st_size > 10_000
    net = load_surrogate(tmp_path / "surrogate.pt")  # the fitted network, usable as a flow map
    x0, u, x1 = one_step_data(load_system("planar3"), net.tau, 64, 5e-4, 1)  # the validation points (seed + 1)
    rmse = (net.step(x0, u) - x1).pow(2).mean(0).sqrt().numpy()
    np.testing.assert_allclose(rmse, m["val_rmse"], rtol=1e-4)
    assert net.meta["training_time_s"] == m["seconds"] and "capacity" in net.meta["trained_with"]


def test_bad_settings_are_refused_in_one_line(make_cfg, tmp_path) -> None:
    with pytest.raises(SettingError, match="points=0: expected an integer >= 1"):
        run_capacity(make_cfg("capacity", ["points=0"]), tmp_path / "a")
    with pytest.raises(SettingError, match="dtype='float16': expected one of float32, float64"):
        run_capacity(make_cfg("capacity", ["dtype=float16"]), tmp_path / "d")
    with pytest.raises(SettingError, match="t_max=0.1 is below the system's tau=0.2"):
        run_capacity(make_cfg("capacity", ["t_max=0.1"]), tmp_path / "b")
    with pytest.raises(ValueError, match="angle_sums must list sums of two or more distinct periodic"):
        run_capacity(make_cfg("capacity", ["system=panda", "system.network.angle_sums=[[0,1]]", *TINY]), tmp_path / "c")


def test_a_fit_with_nothing_left_to_gain_stops_and_says_why(make_cfg, tmp_path) -> None:
    few = ["points=4", "val_points=4", "max_steps=2000", "model.hidden=[16]", "model.auto_scale.samples=64"]
    m = run_capacity(make_cfg("capacity", ["system=planar3", "plots=false", *few]), tmp_path)
    # four points and 200-odd weights: fitted to rounding error long before the step budget, where a line search
    # finds no decrease from a fresh history either
    assert m["stopped"] == "no decrease" and m["resets"] >= 3 and m["steps"] < 2000
    assert np.all(np.array(m["train_rmse"]) < 1e-4 * np.array(m["initial_val_rmse"]))
