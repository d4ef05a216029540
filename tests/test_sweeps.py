"""A failing sweep job is one failed job: the others run to the end, the summary names it and why, and the sweep's
exit code says that one failed (real multirun processes)."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import pytest

from tests.conftest import ROOT, TINY_TRAIN


def _sweep(args: list[str], timeout: int = 600) -> subprocess.CompletedProcess[str]:
    """One multirun of a task, as a user starts it."""
    return subprocess.run([sys.executable, "-m", *args], cwd=ROOT, capture_output=True, text=True, timeout=timeout)


def _summary(sweep_dir) -> dict:
    """sweep_summary.json, after checking the table beside it."""
    assert (sweep_dir / "sweep_summary.md").is_file()
    return json.loads((sweep_dir / "sweep_summary.json").read_text())


def test_closed_loop_sweep_runs_every_job_and_names_the_failed_one(tmp_path):
    # reference.name=nope: a value only the job can refuse (a plant or solver setting of the wrong type or range
    # is refused for the whole sweep before any job runs: test_cli_help)
    r = _sweep([
        "pinnmpc.closed_loop", "-m", "reference.name=default,nope,sine", "max_steps=3", "progress=false",
        "plots=false", f"hydra.sweep.dir={tmp_path}",
    ])  # fmt: skip
    assert r.returncode == 1, r.stderr[-2000:]
    s = _summary(tmp_path)
    assert (s["jobs"], s["ok"], s["failed"], s["exit_code"]) == (3, 2, 1, 1)
    bad = [row for row in s["rows"] if row["verdict"] != "ok"]
    assert len(bad) == 1 and bad[0]["overrides"] == "reference.name=nope" and bad[0]["exit_code"] == 2
    assert "nope" in bad[0]["message"]
    assert "job 1 (reference.name=nope) failed, exit 2" in r.stderr
    for job in ("0", "2"):  # the jobs before and after the bad one ran to the end
        m = json.loads((tmp_path / job / "metrics.json").read_text())
        assert m["status"] == "ok" and m["steps"] == 3
        assert json.loads((tmp_path / job / "job_status.json").read_text())["verdict"] == "ok"
    assert json.loads((tmp_path / "1" / "job_status.json").read_text())["exit_code"] == 2
    assert not (tmp_path / "1" / ".pinnmpc.lock").exists()  # no lock left behind to block or kill another job


def test_a_bad_structured_value_in_a_sweep_is_refused_before_any_job(tmp_path):
    r = _sweep([
        "pinnmpc.closed_loop", "-m", "plant.friction_scale=1,-1,0.5", "max_steps=3", "progress=false",
        "plots=false", f"hydra.sweep.dir={tmp_path / 'sweep'}",
    ])  # fmt: skip
    assert r.returncode == 2 and r.stderr.strip().splitlines() == [
        "pinnmpc.closed_loop: error: plant.friction_scale=-1: expected a finite number >= 0"
    ]
    assert not (tmp_path / "sweep").exists()  # nothing ran


def test_closed_loop_sweep_of_good_jobs_exits_0(tmp_path):
    r = _sweep([
        "pinnmpc.closed_loop", "-m", "plant.friction_scale=1,0.5", "max_steps=2", "progress=false", "plots=false",
        f"hydra.sweep.dir={tmp_path}",
    ])  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]
    assert _summary(tmp_path)["ok"] == 2
    assert "sweep: all 2 jobs ok" in r.stdout


@pytest.mark.parametrize(
    "key, values, good",
    [
        ("controller.horizon", "5,0,-1,abc,2.5,1e9,null", {"5"}),
        ("noise_sigma", "0,nan,inf,-1,'[1,2]',1e-3", {"0", "0.001"}),
    ],
)
def test_fuzz_sweep_values_each_job_ends_clean_or_in_one_line(tmp_path, key, values, good):
    r = _sweep(["pinnmpc.closed_loop", "-m", f"{key}={values}", "max_steps=2", "progress=false", "plots=false",
                f"hydra.sweep.dir={tmp_path}"])  # fmt: skip
    assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr[-2000:]
    s = _summary(tmp_path)
    assert s["jobs"] == len(values.replace("'[1,2]'", "x").split(","))
    for row in s["rows"]:
        value = row["overrides"].split("=", 1)[1]
        if value in good:
            assert row["verdict"] == "ok" and row["status"] == "ok", row
        else:  # bad input: exit 2 and one line naming the key
            assert row["verdict"] == "failed" and row["exit_code"] == 2, row
            assert key in row["message"] and "\n" not in row["message"], row


def test_sigint_stops_the_sweep_and_still_writes_its_summary(tmp_path):
    slow = ["controller.solver=rmsprop", "controller.solvers.rmsprop.max_iter=400", "controller.solvers.rmsprop.tol=0"]
    cmd = [sys.executable, "-m", "pinnmpc.closed_loop", "-m", "seed=0,1,2", *slow, "plots=false"]
    err = tmp_path / "stderr.txt"
    with open(err, "w") as stderr:
        proc = subprocess.Popen([*cmd, f"hydra.sweep.dir={tmp_path / 'sweep'}"], cwd=ROOT, stdout=subprocess.PIPE,
                                stderr=stderr, text=True)  # fmt: skip
        try:
            deadline = time.monotonic() + 240
            while "closed loop:" not in err.read_text() and proc.poll() is None and time.monotonic() < deadline:
                time.sleep(0.2)
            proc.send_signal(signal.SIGINT)
            proc.communicate(timeout=120)
        finally:
            proc.kill()
            proc.wait()
    text = err.read_text()
    assert proc.returncode == 128 + signal.SIGINT, text[-2000:]
    assert "Traceback" not in text and "sweep: stopped at job 0 (interrupted by SIGINT)" in text
    s = _summary(tmp_path / "sweep")
    assert s["interrupted"] == "interrupted by SIGINT" and s["jobs"] == 1  # jobs 1 and 2 never started
    assert s["rows"][0]["verdict"] == "interrupted" and s["rows"][0]["exit_code"] == 130
    assert not (tmp_path / "sweep" / "1").exists()


def _tiny_train(bad: str, *more: str) -> list[str]:
    """A tiny training multirun over data.t_high, one value bad: beyond t_max, which only the job can tell (a value
    that its setting's own check refuses stops the whole sweep before any job runs)."""
    sweep = f"data.t_high=null,{bad}"
    return ["pinnmpc.train", "-m", *TINY_TRAIN, "trainer.max_epochs=1", "progress=false", sweep, *more]


def test_train_sweep_with_a_bad_value_keeps_the_good_run(tmp_path):
    r = _sweep([*_tiny_train("0.3"), f"hydra.sweep.dir={tmp_path}"])
    assert r.returncode == 1, r.stderr[-2000:]
    s = _summary(tmp_path)
    assert (s["ok"], s["failed"]) == (1, 1)
    good, bad = s["rows"]
    assert good["overrides"] == "data.t_high=null" and good["best_val_rmse_position"] is not None
    assert bad["overrides"] == "data.t_high=0.3" and bad["exit_code"] == 2 and "t_high" in bad["message"]
    assert (tmp_path / "0" / "surrogate.pt").is_file()
    assert (tmp_path / "0" / "train.log").read_text().strip()  # the good run's log is whole


@pytest.mark.slow
def test_joblib_grid_with_a_bad_value_runs_every_good_job_and_writes_both_tables(tmp_path):
    r = _sweep([
        *_tiny_train("0.3", "hparams_search=grid"), "hydra.sweeper.params={model.ic:'hard,soft'}",
        f"hydra.sweep.dir={tmp_path}",
    ], timeout=900)  # fmt: skip
    assert r.returncode == 1, r.stderr[-2000:]
    s = _summary(tmp_path)
    assert s["failed"] == 4 and s["ok"] == 4  # model.ic x module.residual_form x t_high: the 0.3 ones failed
    assert all(row["exit_code"] == 2 for row in s["rows"] if row["verdict"] != "ok")
    assert (tmp_path / "sweep_results.md").is_file()  # the training table of the good runs
    for row in s["rows"]:
        if row["verdict"] == "ok":
            assert (tmp_path / row["job"] / "surrogate.pt").is_file()
