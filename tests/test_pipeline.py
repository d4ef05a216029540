"""`stage.split`: a base network and a correction stage on it in one training command, resumable."""

from __future__ import annotations

import json

import pytest

from pinnmpc.surrogate import load_surrogate
from pinnmpc.training.pipeline import duration, seconds
from pinnmpc.training.run import train_command
from pinnmpc.util.checks import SettingError
from tests.conftest import TINY_TRAIN


def test_durations_round_trip():
    assert seconds("01:02:03:04") == 93784.0
    assert duration(93784.4) == "01:02:03:04" and duration(0.2) == "00:00:00:01"


def test_one_command_trains_a_base_then_a_stage_on_it(make_cfg, tmp_path):
    cfg = make_cfg("train", [*TINY_TRAIN, "trainer.max_time=00:00:00:12", "stage.split=0.5", "stage.samples=64"])
    summary = train_command(cfg, tmp_path)
    assert summary["status"] == "ok" and summary["base_run"] == str(tmp_path / "base")
    assert json.loads((tmp_path / "train_metrics.json").read_text())["base_run"] == summary["base_run"]  # the file too
    base = load_surrogate(tmp_path / "base" / "surrogate.pt")
    staged = load_surrogate(tmp_path / "surrogate.pt")
    assert base.model.config["hidden"] == [16, 16] and staged.model.config["hidden"] == [32, 32]  # merged
    base_time = base.meta["training_time_s"]
    assert 0 < base_time < summary["training_time_s"] == staged.meta["training_time_s"]
    assert staged.meta["config"]["stage"]["base"] == str(tmp_path / "base" / "surrogate.pt")
    assert staged.meta["config"]["module"]["robust_delta"] == 1.0


def test_a_split_without_a_time_budget_or_out_of_range_is_refused(make_cfg, tmp_path):
    with pytest.raises(SettingError, match="stage.split needs trainer.max_time"):
        train_command(make_cfg("train", [*TINY_TRAIN, "stage.split=0.5"]), tmp_path)
    with pytest.raises(SettingError, match=r"stage.split=1.5: expected a fraction in \(0, 1\)"):
        train_command(make_cfg("train", [*TINY_TRAIN, "trainer.max_time=00:00:00:10", "stage.split=1.5"]), tmp_path)
    assert not any(tmp_path.iterdir())
