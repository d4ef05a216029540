"""Bad input, signals and shared run dirs: real processes, real files, one-line errors and honest exit codes."""

from __future__ import annotations

import json
import math
import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch

from pinnmpc.cli import (
    LOCK_NAME,
    USER_ERRORS,
    StopSignal,
    acquire,
    check_choices,
    clean,
    discard_own_files,
    guard,
    release,
)
from pinnmpc.simulation.metrics import verdict
from pinnmpc.simulation.robustness import run_robustness
from pinnmpc.simulation.run import run_closed_loop
from pinnmpc.simulation.self_loop import run_self_loop
from pinnmpc.surrogate import SHIPPED, load_surrogate
from pinnmpc.systems import load_system
from pinnmpc.training.job_settings import validate_train
from pinnmpc.training.resume import portable_ckpt
from pinnmpc.training.run import train
from pinnmpc.util.checks import SettingError
from tests.conftest import ROOT, TINY_TRAIN

TINY = [*TINY_TRAIN, "self_loop_figure.every_n_epochs=0"]
ENDLESS_EPOCH = ["module.lbfgs_max_iter=1000000", "module.lbfgs_tolerance_change=0", "module.lbfgs_tolerance_grad=0"]
QUICK = ["max_steps=3", "progress=false", "plots=false"]


def _cli(module: str, *args: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    """A pinnmpc CLI as a user runs it."""
    cmd = [sys.executable, "-m", f"pinnmpc.{module}", *args]
    return subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=timeout)


def _one_line_error(r: subprocess.CompletedProcess[str], prog: str) -> str:
    """The single `prog: error: ...` line of a refused run (and no traceback)."""
    assert "Traceback" not in r.stderr, r.stderr[-3000:]
    lines = [line for line in r.stderr.splitlines() if line.startswith(f"{prog}: error:")]
    assert len(lines) == 1, r.stderr[-3000:]
    return lines[0]


def _wait_for(predicate, proc: subprocess.Popen, timeout: float = 240) -> None:
    """Poll until predicate() holds; the process must still be running."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.poll() is None and not predicate():
        time.sleep(0.05)
    assert proc.poll() is None and predicate(), "the run ended (or never got there) before the signal"


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
    """A run dir of one tiny real training epoch: checkpoints/last.ckpt and surrogate.pt."""
    from hydra import compose, initialize_config_dir

    run_dir = tmp_path_factory.mktemp("trained")
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        train(compose("train", [*TINY, "trainer.max_epochs=1"]), run_dir)
    return run_dir


# 1. a run never deletes what it did not create


@pytest.mark.parametrize(
    ("entry", "override", "message"),
    [("closed_loop", "tau=0", "tau=0: expected a finite number > 0 or null"), ("bench", "threads=0", "threads")],
)
def test_bad_input_leaves_a_chosen_run_dir_as_it_was(tmp_path, entry, override, message):
    run_dir = tmp_path / "mine"
    (run_dir / ".hydra").mkdir(parents=True)
    (run_dir / ".hydra" / "config.yaml").write_text("earlier: run\n")
    (run_dir / "notes.log").write_text("my own notes\n")
    r = _cli(entry, override, "progress=false", f"hydra.run.dir={run_dir}")
    assert r.returncode == 2
    assert message in _one_line_error(r, f"pinnmpc.{entry}")
    assert sorted(p.name for p in run_dir.iterdir()) == [".hydra", "notes.log"]
    assert (run_dir / "notes.log").read_text() == "my own notes\n"
    assert [p.name for p in (run_dir / ".hydra").iterdir()] == ["config.yaml"]
    assert (run_dir / ".hydra" / "config.yaml").read_text() == "earlier: run\n"


def test_a_failed_run_removes_only_the_folders_it_made(tmp_path):
    run_dir = tmp_path / "a" / "b" / "c"
    guard(run_dir, "closed_loop")
    (run_dir / ".hydra").mkdir()  # what Hydra writes next
    (run_dir / ".hydra" / "config.yaml").write_text("x: 1\n")
    (run_dir / "closed_loop.log").write_text("")
    discard_own_files(run_dir)
    assert tmp_path.is_dir() and not (tmp_path / "a").exists()
    kept = tmp_path / "kept"
    guard(kept, "closed_loop")
    (kept / "metrics.json").write_text("{}")  # the run wrote results: they stay
    discard_own_files(kept)
    assert (kept / "metrics.json").is_file() and not (kept / LOCK_NAME).exists()


# 2. signals: a resumable checkpoint or what was reached, and a non-zero exit


def _training_from_epoch_0(run_dir: Path) -> bool:
    """train.log says the first epoch started: its L-BFGS call runs (and with ENDLESS_EPOCH never ends alone)."""
    log = run_dir / "train.log"
    return log.is_file() and "training from epoch 0" in log.read_text()


SIGTERM_MOMENTS = {  # when the signal comes, as seen from outside: each moment of a training, the first epoch's too
    "start-up": lambda run_dir: run_dir.is_dir(),  # Hydra made the run dir: no torch, no network yet
    "setup": lambda run_dir: (run_dir / "tensorboard").is_dir(),  # Lightning's fit began; no epoch has
    "first epoch": _training_from_epoch_0,  # training began: before the first step, or inside the L-BFGS call
}


@pytest.mark.parametrize("moment", sorted(SIGTERM_MOMENTS))
def test_sigterm_during_training_checkpoints_and_says_how_to_resume(make_cfg, tmp_path, moment):
    run_dir = tmp_path / "run"
    cmd = [sys.executable, "-m", "pinnmpc.train", *TINY, *ENDLESS_EPOCH, "trainer.max_epochs=100000"]
    err = tmp_path / "stderr.txt"
    with open(err, "w") as stderr:
        proc = subprocess.Popen([*cmd, f"hydra.run.dir={run_dir}"], cwd=ROOT, stdout=subprocess.DEVNULL, stderr=stderr)
        try:
            _wait_for(lambda: SIGTERM_MOMENTS[moment](run_dir), proc, timeout=600)
            proc.send_signal(signal.SIGTERM)
            rc = proc.wait(timeout=600)  # the (first) L-BFGS call is cut short: a bound for a loaded machine only
        finally:
            proc.kill()
            proc.wait()
    text = err.read_text()
    assert rc == 128 + signal.SIGTERM, text[-3000:]
    assert "Traceback" not in text
    summary = json.loads((run_dir / "train_metrics.json").read_text())
    assert summary["status"] == "interrupted" and summary["signal"] == "SIGTERM"
    assert summary["training_time_s"] > 0
    resume = next(line for line in text.splitlines() if line.startswith("resume with: "))
    args = shlex.split(resume.removeprefix("resume with: "))
    assert args[:3] == ["python", "-m", "pinnmpc.train"] and args[-2:] == ["resume=true", f"hydra.run.dir={run_dir}"]
    assert summary["resume_command"] == resume.removeprefix("resume with: ")
    meta = load_surrogate(run_dir / "surrogate.pt").meta
    assert (meta["status"], meta["signal"]) == ("interrupted", "SIGTERM")  # the network's meta says the same
    last = torch.load(run_dir / "checkpoints" / "last.ckpt", weights_only=True)
    assert last["epoch"] == 0 and not (run_dir / LOCK_NAME).exists()
    # the checkpoint resumes; a budget it has spent is refused before anything in the run dir changes
    before = {f: f.stat().st_mtime_ns for f in run_dir.rglob("*") if f.is_file()}
    with pytest.raises(ValueError, match="has trained 1 epochs, so trainer.max_epochs=1 is reached"):
        train(make_cfg("train", [*TINY, *ENDLESS_EPOCH, "trainer.max_epochs=1", "resume=true"]), run_dir)
    assert before == {f: f.stat().st_mtime_ns for f in run_dir.rglob("*") if f.is_file()}
    done = train(make_cfg("train", [*TINY, "trainer.max_epochs=2", "resume=true"]), run_dir)
    assert done["status"] == "ok" and done["epochs"] == 2


class _SigtermAt(L.Callback):
    """Sends SIGTERM to this process once, from one Lightning hook: a moment of the first epoch, exactly."""

    def __init__(self, hook: str) -> None:
        self.sent = False
        setattr(self, hook, self._send)

    def _send(self, *_: object) -> None:
        if not self.sent:
            self.sent = True
            os.kill(os.getpid(), signal.SIGTERM)


FIRST_EPOCH_MOMENTS = {  # (hook, before the other callbacks' hooks): the moments from outside are windows
    "training starts, the signals still Lightning's": ("on_train_start", True),
    "training starts, the signals taken back": ("on_train_start", False),
    "the epoch starts": ("on_train_epoch_start", False),
    "the step starts": ("on_train_batch_start", False),
    "validation": ("on_validation_start", False),
}


@pytest.mark.parametrize("moment", sorted(FIRST_EPOCH_MOMENTS))
def test_sigterm_at_each_moment_of_the_first_epoch_leaves_its_checkpoint(make_cfg, tmp_path, monkeypatch, moment):
    from pinnmpc.training import run

    hook, first = FIRST_EPOCH_MOMENTS[moment]
    sender = _SigtermAt(hook)
    build = run.build_trainer
    monkeypatch.setattr(
        run, "build_trainer", lambda cfg, cbs, *a: build(cfg, [sender, *cbs] if first else [*cbs, sender], *a)
    )
    run_dir = tmp_path / "run"
    cfg = make_cfg("train", [*TINY, *ENDLESS_EPOCH, "trainer.max_epochs=100000", "progress=false"])
    with StopSignal() as stop:
        summary = train(cfg, run_dir, stop=stop, overrides=["progress=false"])
    assert sender.sent and stop.name == "SIGTERM"
    assert summary["status"] == "interrupted" and summary["epochs"] == 1, summary
    assert summary["resume_command"] and summary["resume_command"].endswith(f"hydra.run.dir={run_dir}")
    assert torch.load(run_dir / "checkpoints" / "last.ckpt", weights_only=True)["epoch"] == 0
    assert (run_dir / "train.log").read_text().splitlines()[-1].endswith("training ended after epoch 0")


def test_a_run_killed_after_its_budget_resumes_to_write_its_network(make_cfg, tmp_path):
    run_dir = tmp_path / "run"
    first = train(make_cfg("train", [*TINY, "trainer.max_epochs=2"]), run_dir)
    # killed after its last epoch's checkpoint, before surrogate.pt and train_metrics.json were written
    (run_dir / "surrogate.pt").unlink()
    (run_dir / "train_metrics.json").unlink()
    ckpts = {f: f.stat().st_mtime_ns for f in (run_dir / "checkpoints").iterdir()}
    done = train(make_cfg("train", [*TINY, "trainer.max_epochs=2", "resume=true"]), run_dir)
    assert done["status"] == "ok" and done["finished_from_checkpoint"] and done["epochs"] == 2
    assert done["best_val_rmse_position"] == pytest.approx(first["best_val_rmse_position"])
    assert 0 < done["training_time_s"] <= first["training_time_s"]  # as counted at its last checkpoint
    assert ckpts == {f: f.stat().st_mtime_ns for f in (run_dir / "checkpoints").iterdir()}  # nothing trained
    net = load_surrogate(run_dir / "surrogate.pt")
    assert net.meta["finished_from_checkpoint"] and json.loads((run_dir / "train_metrics.json").read_text())
    # with its network written, a spent budget is refused again
    with pytest.raises(ValueError, match="trainer.max_epochs=2 is reached"):
        train(make_cfg("train", [*TINY, "trainer.max_epochs=2", "resume=true"]), run_dir)


def test_shipped_training_checkpoints_hold_no_absolute_path_and_still_resume(make_cfg, tmp_path):
    shipped = sorted((ROOT / "checkpoints" / "train").glob("*.ckpt"))
    assert shipped
    for f in shipped:
        ckpt = torch.load(f, map_location="cpu", weights_only=True)
        paths = [v for state in ckpt["callbacks"].values() if isinstance(state, dict) for v in state.values()
                 if isinstance(v, str) and "/" in v]  # fmt: skip
        assert paths and not any(Path(v).is_absolute() for v in paths), (f.name, paths)
    first = tmp_path / "first"
    train(make_cfg("train", [*TINY, "trainer.max_epochs=1"]), first)
    ckpt = portable_ckpt(torch.load(first / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True))
    assert ckpt["callbacks"] and str(first) not in repr(ckpt["callbacks"])
    torch.save(ckpt, tmp_path / "shipped.ckpt")
    done = train(make_cfg("train", [*TINY, "trainer.max_epochs=2", f"ckpt_path={tmp_path / 'shipped.ckpt'}"]),
                 tmp_path / "second")  # fmt: skip
    assert done["status"] == "ok" and done["epochs"] == 2
    assert done["resumed_best_val_rmse_position"] is not None


def test_sigint_during_a_closed_loop_keeps_what_was_reached(tmp_path):
    run_dir = tmp_path / "run"
    slow = ["controller.solver=rmsprop", "controller.solvers.rmsprop.max_iter=400", "controller.solvers.rmsprop.tol=0"]
    err = tmp_path / "stderr.txt"
    with open(err, "w") as stderr:
        cmd = [sys.executable, "-m", "pinnmpc.closed_loop", *slow, "plots=false", f"hydra.run.dir={run_dir}"]
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=stderr, text=True)
        try:
            _wait_for(lambda: "closed loop:" in err.read_text(), proc)
            proc.send_signal(signal.SIGINT)
            out, _ = proc.communicate(timeout=120)
        finally:
            proc.kill()
            proc.wait()
    assert proc.returncode == 128 + signal.SIGINT, err.read_text()[-3000:]
    assert "interrupted by SIGINT" in err.read_text() and "Traceback" not in err.read_text()
    assert any(line.startswith("interrupted: ") for line in out.splitlines())  # the headline
    m = json.loads((run_dir / "metrics.json").read_text())
    traj = np.load(run_dir / "trajectory.npz")
    assert m["status"] == "interrupted" and m["steps"] < 100
    assert traj["x"].shape == (m["steps"] + 1, 4) and traj["u"].shape == (m["steps"], 2)
    assert np.all(np.isfinite(traj["u"])) and np.all(np.abs(traj["u"]) <= 0.5)


def test_stop_signal_asks_once_then_stops_at_once():
    before = signal.getsignal(signal.SIGTERM)
    with StopSignal() as stop:
        os.kill(os.getpid(), signal.SIGTERM)
        _settle(lambda: stop.requested)
        assert stop.requested and stop.name == "SIGTERM" and stop.exit_code == 143
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)
            _settle(lambda: False)
    assert signal.getsignal(signal.SIGTERM) is before


def _settle(done) -> None:
    """Give a signal sent to this process a moment to reach its Python handler."""
    for _ in range(100):
        if done():
            return
        time.sleep(0.01)


# 3. silent failures of the closed loop


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("noise_sigma=nan", "noise_sigma=nan: expected a finite number >= 0"),
        ("noise_sigma=-1", "noise_sigma=-1: expected a finite number >= 0"),
        ("max_steps=0", "max_steps=0: expected an integer >= 1 or null"),
        ("controller.u_low=[nan,nan]", "controller.u_low=[nan, nan]: expected null or a list of 2 entries"),
        ("tau=abc", "tau='abc': expected a finite number > 0 or null"),
        ("tau=0", "tau=0: expected a finite number > 0"),
        ("seed=abc", "seed='abc': expected an integer"),
        ("controller.Q=abc", "controller.Q='abc': expected 4 finite numbers >= 0"),
        ("controller.Q=[1,1,0]", "controller.Q=[1, 1, 0]: expected 4 finite numbers"),
        ("controller.R=[1e-6,abc]", "controller.R=[1e-06, 'abc']: expected 2 finite numbers"),
        ("controller.horizon=abc", "controller.horizon='abc': expected a whole number >= 1"),
        ("controller.horizon=2.5", "controller.horizon=2.5: expected a whole number >= 1"),
        ("threads=0", "threads=0: expected an integer >= 1"),
        ("plant.method=RK99", "plant.method='RK99': expected one of RK45"),
        ("failure.max_fallback_fraction=2", "failure.max_fallback_fraction=2: expected a finite number in [0, 1]"),
        (
            "controller.u_low=[0.3,0.3] controller.u_high=[0.1,0.1]",
            "controller.u_low=[0.3, 0.3] exceeds controller.u_high",
        ),
    ],
)
def test_bad_closed_loop_settings_are_refused_before_any_work(make_cfg, tmp_path, override, message):
    with pytest.raises(SettingError) as e:
        run_closed_loop(make_cfg("closed_loop", [*QUICK, *override.split()]), tmp_path)
    assert str(e.value).startswith(message) and "\n" not in str(e.value)
    assert not list(tmp_path.iterdir())


def test_input_bounds_beyond_the_training_box_need_an_explicit_override(make_cfg, tmp_path, caplog):
    wide = [*QUICK, "controller.u_low=[-5,-5]", "controller.u_high=[5,5]"]
    with pytest.raises(SettingError, match="beyond the surrogate's training input box.*allow_inputs_outside_box=true"):
        run_closed_loop(make_cfg("closed_loop", wide), tmp_path)
    m = run_closed_loop(make_cfg("closed_loop", [*wide, "allow_inputs_outside_box=true"]), tmp_path)
    assert m["input_bounds_outside_box"] is True
    assert any(r.levelname == "WARNING" and "extrapolation" in r.getMessage() for r in caplog.records)
    u = np.load(tmp_path / "trajectory.npz")["u"]
    assert np.all(np.isfinite(u)) and np.all(np.abs(u) <= 5.0)


def test_a_long_horizon_is_warned_about_before_the_run(make_cfg, tmp_path, caplog):
    run_closed_loop(make_cfg("closed_loop", [*QUICK, "max_steps=2"]), tmp_path / "a")
    assert not any("long_horizon" in r.getMessage() for r in caplog.records)
    m = run_closed_loop(make_cfg("closed_loop", [*QUICK, "max_steps=2", "long_horizon=4"]), tmp_path / "b")
    warned = [r.getMessage() for r in caplog.records if "long_horizon" in r.getMessage()]
    assert warned == ["controller.horizon=5 is above long_horizon=4: each solve costs H^2 to H^3 and may stop at its "
                      "iteration cap unconverged; expected a horizon of a few to a few dozen steps (raise long_horizon "
                      "to silence this)"] and m["status"] == "ok"  # fmt: skip
    with pytest.raises(SettingError, match="long_horizon=0: expected an integer >= 1"):
        run_closed_loop(make_cfg("closed_loop", [*QUICK, "long_horizon=0"]), tmp_path / "c")


@pytest.fixture(scope="module")
def nan_surrogate(tmp_path_factory) -> Path:
    """A surrogate file whose network predicts NaN everywhere: every OCP solve fails."""
    s = load_surrogate()
    for p in s.model.parameters():
        p.data.fill_(math.nan)
    return s.save(tmp_path_factory.mktemp("nan") / "nan.pt")


def test_a_run_where_every_step_fell_back_fails(make_cfg, tmp_path, nan_surrogate):
    cfg = make_cfg("closed_loop", [*QUICK, f"checkpoint={nan_surrogate}", "failure.max_fallback_fraction=1.0"])
    m = run_closed_loop(cfg, tmp_path)
    assert m["status"].startswith("failed: every one of the 3 steps fell back")
    assert m["fallback_fraction"] == 1.0 and m["fallbacks"] == 3
    assert json.loads((tmp_path / "metrics.json").read_text())["status"] == m["status"]
    u = np.load(tmp_path / "trajectory.npz")["u"]
    assert np.all(np.isfinite(u)) and np.all(np.abs(u) <= 0.5)
    r = _cli("closed_loop", *QUICK, f"checkpoint={nan_surrogate}", f"hydra.run.dir={tmp_path / 'cli'}")
    assert r.returncode == 1, r.stderr[-2000:]
    assert any(line.startswith("failed: every one of the 3 steps fell back") for line in r.stdout.splitlines())


def test_the_fallback_threshold_decides_the_verdict():
    m = {"status": "ok", "steps": 10, "fallbacks": 2}
    assert verdict(m, 0.1).startswith("failed: 2 of 10 steps fell back (20% > failure.max_fallback_fraction=0.1)")
    assert verdict(m, 0.2) == "ok"
    assert verdict({**m, "fallbacks": 10}, 1.0).startswith("failed: every one")
    assert verdict({**m, "status": "interrupted", "fallbacks": 10}, 0.1) == "interrupted"


# 4. resume never silently starts over; bad checkpoints are one line


def test_resume_without_a_last_checkpoint_is_refused_and_the_run_dir_kept(tmp_path):
    run_dir = tmp_path / "mine"
    run_dir.mkdir()
    (run_dir / "notes.log").write_text("mine\n")
    r = _cli("train", "resume=true", f"hydra.run.dir={run_dir}")
    assert r.returncode == 2
    line = _one_line_error(r, "pinnmpc.train")
    assert f"resume=true but {run_dir}/checkpoints/last.ckpt does not exist" in line
    assert [p.name for p in run_dir.iterdir()] == ["notes.log"]


@pytest.mark.parametrize("kind", ["surrogate", "text", "truncated", "other_network"])
def test_a_checkpoint_that_cannot_resume_is_one_line(make_cfg, tmp_path, trained, kind):
    last = trained / "checkpoints" / "last.ckpt"
    overrides, path = [*TINY, "trainer.max_epochs=2"], tmp_path / "file.ckpt"
    if kind == "surrogate":
        path, expected = trained / "surrogate.pt", "is an exported surrogate"
    elif kind == "text":
        path.write_text("hello\n")
        expected = "is not a torch file"
    elif kind == "truncated":
        path.write_bytes(last.read_bytes()[: last.stat().st_size // 2])
        expected = "cannot be read"
    else:
        path, expected = last, "holds another network"
        overrides = [*overrides, "model.hidden=[8,8]"]
    with pytest.raises(ValueError) as e:
        train(make_cfg("train", [*overrides, f"ckpt_path={path}"]), tmp_path / "run")
    assert f"ckpt_path={path} {expected}" in str(e.value) and "\n" not in str(e.value)
    assert "expected" in str(e.value)


def test_truncated_last_checkpoint_on_resume_is_one_line(make_cfg, tmp_path, trained):
    data = (trained / "checkpoints" / "last.ckpt").read_bytes()
    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints" / "last.ckpt").write_bytes(data[:1000])
    with pytest.raises(ValueError, match=r"resume=true: .*last.ckpt cannot be read"):
        train(make_cfg("train", [*TINY, "resume=true"]), tmp_path)


def test_training_time_after_a_kill_is_the_training_not_this_process(make_cfg, tmp_path):
    cmd = [sys.executable, "-m", "pinnmpc.train", *TINY, "trainer.max_epochs=100000", f"hydra.run.dir={tmp_path}"]
    last = tmp_path / "checkpoints" / "last.ckpt"
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        _wait_for(lambda: last.is_file() and torch.load(last, weights_only=True)["epoch"] >= 8, proc)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()
    killed = torch.load(last, weights_only=True)
    counted = killed["callbacks"]["Timer"]["time_elapsed"]["train"]
    assert counted > 0  # a Timer is there without max_time too
    summary = train(make_cfg("train", [*TINY, f"trainer.max_epochs={killed['epoch'] + 2}", "resume=true"]), tmp_path)
    assert counted < summary["training_time_s"] <= counted + summary["wall_time_s"]


# 5. make: each override once, as its own argument; clean keeps live runs and shipped checkpoints


def _make_n(*args: str) -> list[str]:
    """The arguments make would hand the Python module (make -n: nothing runs)."""
    r = subprocess.run(["make", "-n", *args], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert r.returncode == 0, r.stderr
    line = next(line for line in r.stdout.splitlines() if " -m pinnmpc." in line)
    words = shlex.split(line)
    return words[words.index("-m") + 2 :]


def test_make_passes_each_override_once_as_its_own_argument():
    budget = "trainer.max_time=00:00:01:00"
    assert _make_n("train", "seed=1", budget) == ["seed=1", budget]
    assert _make_n("train", f"ARGS=seed=1 {budget} model.hidden=[8,8]") == ["seed=1", budget, "model.hidden=[8,8]"]
    assert _make_n("closed-loop", "controller.Q=[1, 1, 0, 0]", "VENV=.venv") == ["controller.Q=[1, 1, 0, 0]"]
    assert _make_n("train") == []


def test_clean_keeps_live_runs_and_shipped_checkpoints(tmp_path):
    r = subprocess.run(["make", "-n", "clean"], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert "pinnmpc.cli clean outputs" in r.stdout and "rm -rf outputs" not in r.stdout
    outputs = tmp_path / "outputs"
    for d in ("train/old/checkpoints", "sweeps/2026/0", "closed_loop/x", "train/live"):
        (outputs / d).mkdir(parents=True)
    (outputs / "train/old/checkpoints/last.ckpt").write_bytes(b"x")
    (outputs / "sweeps/2026/0/surrogate.pt").write_bytes(b"x")
    (outputs / "train/live/metrics.json").write_text("{}")
    (outputs / "shipped.pt").symlink_to(SHIPPED)
    held = acquire(outputs / "train/live")
    try:
        kept = clean([outputs])
    finally:
        os.close(held)
    assert SHIPPED.is_file()
    assert not (outputs / "train/old").exists() and not (outputs / "sweeps").exists()
    assert (outputs / "train/live/metrics.json").is_file() and outputs / "train/live" in kept


# 6. settings of the other entry points; a run dir that cannot be one


def test_a_stage_may_start_exactly_at_its_base(make_cfg) -> None:
    validate_train(make_cfg("train", ["stage.last_layer_gain=0"]), load_system("powercube"))  # zero-init: allowed


@pytest.mark.parametrize(
    ("entry", "override", "message"),
    [
        ("train", "threads=-1", "threads=-1: expected an integer >= 0"),
        ("train", "seed=abc", "seed='abc': expected an integer"),
        ("train", "trainer.max_time=soon", "trainer.max_time='soon': expected a duration DD:HH:MM:SS"),
        ("train", "t_max=0.1", "t_max=0.1 is below the system's tau=0.2"),
        (
            "train",
            "module.anchor_state_weight=[1]",
            "module.anchor_state_weight=[1.0]: expected null or a list of 4 entries",
        ),
        ("train", "module.weight_physics=-1", "module.weight_physics=-1.0: expected a finite number >= 0"),
        ("train", "module.weight_anchor=nan", "module.weight_anchor=nan: expected a finite number >= 0"),
        ("train", "module.lbfgs_lr=-1", "module.lbfgs_lr=-1.0: expected a finite number > 0"),
        ("train", "module.lbfgs_max_iter=0", "module.lbfgs_max_iter=0: expected an integer >= 1"),
        ("train", "data.resample_every=-1", "data.resample_every=-1: expected an integer >= 0"),
        ("train", "trainer.max_epochs=0", "trainer.max_epochs=0: expected -1 (no limit) or an integer >= 1"),
        ("train", "trainer.max_time=00:00:00:00", "trainer.max_time='00:00:00:00': expected a duration"),
        ("train", "stage.last_layer_gain=-1", "stage.last_layer_gain=-1: expected a finite number >= 0"),
        ("train", "system=planar3 stage.split=0.5", "stage.split/stage.base with model.prior=frozen_arm"),
        ("self_loop", "steps=2.5", "steps=2.5: expected an integer >= 2"),
        ("self_loop", "x0=[0,0]", "x0=[0, 0]: expected a list of 4 entries (nx)"),
        ("self_loop", "amplitude=[nan,1]", "amplitude=[nan, 1]: expected a list of 2 entries (nu)"),
        ("robustness", "robustness.noise_sigma=[-1]", "robustness.noise_sigma=[-1]: expected a non-empty list"),
        ("robustness", "robustness.bound=0", "robustness.bound=0: expected a finite number > 0"),
    ],
)
def test_bad_settings_of_every_entry_point_are_refused(make_cfg, tmp_path, entry, override, message):
    run = {"train": train, "self_loop": run_self_loop, "robustness": run_robustness}[entry]
    with pytest.raises(SettingError) as e:
        run(make_cfg(entry, override.split(" ")), tmp_path)
    assert str(e.value).startswith(message)
    assert not list(tmp_path.iterdir())


def test_a_run_dir_that_cannot_be_one_is_one_line(tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("mine\n")
    r = _cli("closed_loop", "max_steps=1", f"hydra.run.dir={afile}")
    assert r.returncode == 2
    assert f"hydra.run.dir={afile} is a file" in _one_line_error(r, "pinnmpc.closed_loop")
    assert afile.read_text() == "mine\n"
    with pytest.raises(ValueError, match="cannot be created"):
        guard(afile / "sub", "closed_loop")


# 7. one live run per run dir


def test_a_run_dir_a_live_run_holds_is_refused_and_a_dead_ones_taken_over(tmp_path):
    run_dir = tmp_path / "shared"
    run_dir.mkdir()
    held = acquire(run_dir)  # this test process is the live run
    try:
        r = _cli("closed_loop", "max_steps=1", f"hydra.run.dir={run_dir}")
    finally:
        os.close(held)
    assert r.returncode == 2
    assert f"is in use by another live run (PID {os.getpid()}" in _one_line_error(r, "pinnmpc.closed_loop")
    assert [p.name for p in run_dir.iterdir()] == [LOCK_NAME]  # nothing was written into it
    (run_dir / LOCK_NAME).write_text("999999999\n")  # left by a killed run: no one holds the lock
    guard(run_dir, "closed_loop")
    assert (run_dir / LOCK_NAME).read_text().strip() == str(os.getpid())
    release(run_dir.absolute())
    assert not (run_dir / LOCK_NAME).exists()


# fuzz: malformed references and settings end in one line, or in a run that kept every input finite and bounded


def _malformed_references(folder: Path, rng: np.random.Generator) -> list[Path]:
    """References a user might pass by mistake, plus a few valid ones."""
    t = np.arange(0.0, 3.0, 0.1)
    x = np.zeros((len(t), 4))
    x[:, 0] = 0.3 * np.sin(t)
    cases: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    bad = x.copy()
    bad[rng.integers(len(t)), rng.integers(4)] = np.nan
    cases["nan.npz"] = (t, bad)
    cases["shape.npz"] = (t, x[:, :3])
    cases["transposed.npz"] = (t, x.T)
    cases["decreasing.npz"] = (t[::-1], x)
    cases["short.npz"] = (t[:3], x[:3])
    cases["huge.npz"] = (t, x * 1e6)
    cases["valid.npz"] = (t, x)
    paths = []
    for name, (tt, xx) in cases.items():
        np.savez(folder / name, t=tt, x=xx)
        paths.append(folder / name)
    np.savez(folder / "no_x.npz", t=t, y=x)
    (folder / "garbage.npz").write_bytes(rng.bytes(200))
    header = "t,alpha,beta,dalpha,dbeta"
    rows = "\n".join(",".join(f"{v:g}" for v in (tt, *xx)) for tt, xx in zip(t, x))
    (folder / "valid.csv").write_text(f"{header}\n{rows}\n")
    (folder / "columns.csv").write_text(f"time,a,b,c,d\n{rows}\n")
    (folder / "text.csv").write_text(f"{header}\n0,a,b,c,d\n1,e,f,g,h\n")
    (folder / "empty.csv").write_text("")
    (folder / "nan.csv").write_text(f"{header}\n{rows.replace('0,', 'nan,', 1)}\n")
    files = ("no_x.npz", "garbage.npz", "valid.csv", "columns.csv", "text.csv", "empty.csv", "nan.csv")
    return [*paths, *(folder / n for n in files)]


BAD_VALUES = ["nan", "inf", "-1", "0", "abc", "2.5", "[]", "[1]", "[nan,nan]", "1e300", "null", "[0.1,-0.1]"]
KEYS = [
    "noise_sigma", "max_steps", "seed", "tau", "threads", "controller.horizon", "controller.Q", "controller.R",
    "controller.u_low", "controller.u_high", "plant.rtol", "plant.friction_scale", "plant.mass_scale",
]  # fmt: skip


def _bounded_run(run_dir: Path, low: list[float], high: list[float]) -> None:
    """Every plant input the run applied was finite and inside the bounds."""
    u = np.load(run_dir / "trajectory.npz")["u"]
    assert np.all(np.isfinite(u)) and np.all(u >= np.array(low) - 1e-12) and np.all(u <= np.array(high) + 1e-12)


def test_fuzz_malformed_references_and_settings(make_cfg, tmp_path, capsys):
    rng = np.random.default_rng(7)
    refs = _malformed_references(tmp_path, rng)
    cases = [[f"reference.path={p}"] for p in refs]
    cases += [[f"{k}={rng.choice(BAD_VALUES)}" for k in rng.choice(KEYS, size=2, replace=False)] for _ in range(16)]
    outcomes = {"refused": 0, "ran": 0}
    for i, overrides in enumerate(cases):
        run_dir = tmp_path / f"run{i}"
        try:  # what the CLI checks before Hydra composes: a structured setting (plant.*) of a wrong type or range
            check_choices("pinnmpc.closed_loop", overrides)
        except SystemExit as stop:
            said = capsys.readouterr().err.strip().splitlines()
            assert stop.code == 2 and len(said) == 1 and said[0].startswith("pinnmpc.closed_loop: error: "), said
            outcomes["refused"] += 1
            continue
        try:
            run_closed_loop(make_cfg("closed_loop", [*QUICK, *overrides]), run_dir)
        except USER_ERRORS as e:  # run_cli turns these into one line and exit code 2
            message = str(e).strip()
            assert message and "\n" not in message, (overrides, message)
            outcomes["refused"] += 1
            continue
        cfg = make_cfg("closed_loop", overrides)
        low = [-0.5, -0.5] if cfg.controller.u_low is None else list(cfg.controller.u_low)
        high = [0.5, 0.5] if cfg.controller.u_high is None else list(cfg.controller.u_high)
        _bounded_run(run_dir, low, high)
        outcomes["ran"] += 1
    assert outcomes["refused"] > 10 and outcomes["ran"] >= 2, outcomes
    # the same through the real CLI: one line on stderr, non-zero exit
    for overrides in ([f"reference.path={tmp_path / 'decreasing.npz'}"], ["noise_sigma=nan", "controller.R=[1]"]):
        r = _cli("closed_loop", *QUICK, *overrides, f"hydra.run.dir={tmp_path / 'cli'}")
        assert r.returncode == 2, r.stderr[-2000:]
        _one_line_error(r, "pinnmpc.closed_loop")
        assert not (tmp_path / "cli").exists()
