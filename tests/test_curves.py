"""Accuracy-against-time plots read a real training run's TensorBoard log."""

from __future__ import annotations

import numpy as np

from pinnmpc.curves import main
from pinnmpc.training.curves import read_curve
from pinnmpc.training.run import train
from tests.conftest import TINY_TRAIN


def test_a_training_run_logs_each_epoch_and_gives_a_curve_plot_and_csv(make_cfg, tmp_path):
    run = tmp_path / "run"
    summary = train(make_cfg("train", [*TINY_TRAIN, "trainer.max_epochs=3"]), run)
    log = (run / "train.log").read_text().splitlines()  # the run's history, in its run dir
    assert "optimizer ssbfgs" in log[0] and any("epoch 2 " in line and "val rmse alpha=" in line for line in log)
    assert any(line.endswith("training ended after epoch 2") for line in log)  # the last epoch logged
    curve = read_curve(run, "tiny")
    assert len(curve.minutes) == 3 and np.all(np.diff(curve.minutes) >= 0) and curve.minutes[0] > 0
    assert np.all(curve.position > 0) and np.all(curve.velocity > 0)
    assert curve.minutes[-1] * 60 <= summary["training_time_s"]  # training time: the set-up before it left out
    out = tmp_path / "curves.png"
    assert main([f"{run}=tiny", "--out", str(out)]) == 0
    assert out.read_bytes().startswith(b"\x89PNG")
    rows = out.with_suffix(".csv").read_text().splitlines()
    assert rows[0] == "run,minutes,rmse_position,rmse_velocity" and len(rows) == 4
    assert main([f"{run}=tiny", f"{run}=tiny", "--out", str(tmp_path / "twice.png")]) == 2  # one label, two runs
    assert not (tmp_path / "twice.png").exists()


def test_a_dir_that_is_no_training_run_is_named_in_the_error(tmp_path, capsys):
    assert main([str(tmp_path), "--out", str(tmp_path / "x.png")]) == 2
    assert f"{tmp_path} has no tensorboard/ folder" in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists()
    assert main([str(tmp_path / "gone"), "--out", str(tmp_path / "x.png")]) == 2
    assert f"pinnmpc.curves: error: {tmp_path / 'gone'} does not exist" in capsys.readouterr().err
    assert main([str(tmp_path), "--out", str(tmp_path / "x.txt")]) == 2
    assert "--out" in capsys.readouterr().err and not (tmp_path / "x.txt").exists()
