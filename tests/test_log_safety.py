"""Robot logs are never lost or silently misused: collect never replaces a log and keeps its finished episodes when
killed, identify never overwrites a config unasked, and every reader refuses a set of logs it cannot fit in one
line naming the file. Real collect runs on the simulated plant, real identify, real processes."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mujoco")

from pinnmpc import load_system  # noqa: E402 (after the skip)
from pinnmpc.cli import run_cli  # noqa: E402
from pinnmpc.robot_data.collect import collect, run_collect  # noqa: E402
from pinnmpc.robot_data.identify_job import run_identify  # noqa: E402
from pinnmpc.robot_data.logs import RobotLog, read_log, read_logs, write_log  # noqa: E402
from tests.conftest import ROOT, TINY_TRAIN  # noqa: E402

TINY = ["system=planar3", "episodes.kinds=[excitation]", "excitation.duration=0.5", "fine=10", "progress=false"]
FAST_FIT = ["system=planar3", "min_speed=0", "validation_periods=0", "max_samples=2000"]


def _collect_to(make_cfg: Callable, folder: Path, extra: list[str]) -> Path:
    """A real 3 s collect (excitation only) into folder; its .npz."""
    run_collect(make_cfg("collect", [*TINY, "robot_time=3", *extra]), folder)
    return folder / "robot_log.npz"


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Three real logs: seed 0 and seed 1 of the model as the robot, seed 2 of the lab robot, and seed 0 again."""
    from hydra import compose, initialize_config_dir

    def make_cfg(name: str, overrides: list[str]) -> object:
        """As conftest's make_cfg (a module fixture cannot use that function-scoped one)."""
        with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
            return compose(config_name=name, overrides=overrides)

    base = tmp_path_factory.mktemp("logs")
    runs = {"a": ["seed=0"], "b": ["seed=1"], "lab": ["seed=2", "plant.robot=lab"], "again": ["seed=0"]}
    return {key: _collect_to(make_cfg, base / key, extra) for key, extra in runs.items()}


def _one_error_line(capsys: pytest.CaptureFixture, body: Callable[[], object], prog: str) -> str:
    """body under the commands' run_cli: exit 2 and exactly one line `prog: error: ...` on stderr."""
    with pytest.raises(SystemExit) as done:
        run_cli(body, prog)
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip() and "WARNING" not in line]
    assert done.value.code == 2 and len(lines) == 1 and lines[0].startswith(f"{prog}: error: "), err
    return lines[0]


def _edited(log: RobotLog, folder: Path, name: str, **changes: object) -> Path:
    """The log with some arrays changed, written as a new log; its .npz."""
    write_log(folder / name, replace(log, meta=dict(log.meta), **changes))
    return folder / f"{name}.npz"


def _bad_sets(logs: dict[str, Path], tmp: Path) -> dict[str, tuple[list[Path], str]]:
    """Each set of logs identify (and every reader) must refuse, and the piece of the one line it gives."""
    system = load_system("planar3")
    log = read_log(logs["a"], system)
    no_fine = tmp / "no_fine"
    no_fine.mkdir()
    (no_fine / "robot_log.csv").write_bytes(logs["a"].with_suffix(".csv").read_bytes())  # its _fine.csv left behind
    garbage = log.x_fine.copy()
    garbage[3, 4] = 1e3  # a sample between two control times
    deg = 180 / np.pi
    one = dict(t=log.t[:1], x=log.x[:1], u=log.u[:1], episode=log.episode[:1], t_fine=None, x_fine=None,
               episode_fine=None)  # fmt: skip
    return {
        "listed twice": ([logs["a"], logs["a"]], f"robot log {logs['a']}: listed twice (logs[0] and logs[1])"),
        "same seed": ([logs["a"], logs["again"]], f"robot log {logs['again']}: episode 0 repeats episode 0 of"),
        "npz and csv": ([logs["a"], logs["a"].with_suffix(".csv")], "(the same samples: a copy, or a collect with"),
        "two robots": ([logs["a"], logs["lab"]], "plant.robot='lab', but"),
        "no fine part": ([no_fine / "robot_log.csv"], "meta fine=10 but robot_log_fine.csv is missing"),
        "degrees": (
            [_edited(log, tmp, "deg", x=log.x * deg, x_fine=log.x_fine * deg)],
            "farther outside the state box",
        ),
        "garbage fine": ([_edited(log, tmp, "garbage", x_fine=garbage)], "fine part: v_joint2 = 1000 at t="),
        "one sample": ([_write_meta(log, tmp, one)], "1 sample(s) and no hold period"),
    }


def _write_meta(log: RobotLog, tmp: Path, arrays: dict) -> Path:
    """A log of the given arrays at the control rate alone (meta fine=1)."""
    write_log(tmp / "one", RobotLog(**arrays, meta={**log.meta, "fine": 1}))
    return tmp / "one.npz"


CASES = ["listed twice", "same seed", "npz and csv", "two robots", "no fine part", "degrees", "garbage fine",
         "one sample"]  # fmt: skip


@pytest.mark.parametrize("case", CASES)
def test_identify_refuses_logs_it_cannot_fit_in_one_line(case, logs, make_cfg, tmp_path, capsys) -> None:
    paths, expected = _bad_sets(logs, tmp_path)[case]
    out = tmp_path / "fit" / "planar3_lab.yaml"
    cfg = make_cfg("identify", [*FAST_FIT, f"logs=[{','.join(map(str, paths))}]", f"out={out}"])
    line = _one_error_line(capsys, lambda: run_identify(cfg, tmp_path / "run"), "pinnmpc.identify")
    assert expected in line and "; expected " in line, line
    assert not out.exists()


def test_training_and_the_bench_read_logs_through_the_same_check(logs, make_cfg, tmp_path) -> None:
    from pinnmpc.bench.robot import held_out_rmse
    from pinnmpc.training.run import train

    system = load_system("planar3")
    with pytest.raises(ValueError, match="repeats episode 0 of"):
        held_out_rmse(system, {}, [str(logs["a"]), str(logs["again"])])
    overrides = [*TINY_TRAIN, "system=planar3", "model.auto_scale.h=1e-3", "data.n_anchor=0", "progress=false",
                 "trainer.max_epochs=1", f"data.logs=[{logs['a']},{logs['lab']}]"]  # fmt: skip
    with pytest.raises(ValueError, match=r"plant\.robot='lab', but .* expected logs of one robot"):
        train(make_cfg("train", overrides), tmp_path / "train")
    assert len(read_logs([logs["a"], logs["b"]], system)) == 2  # two seeds of one robot: fine together


def test_identify_never_overwrites_unasked_and_records_a_cut_short_log(logs, make_cfg, tmp_path, capsys) -> None:
    system = load_system("planar3")
    log = read_log(logs["b"], system)
    short = tmp_path / "short"
    why = "interrupted by SIGINT: 3 of 300 s of robot time logged"
    write_log(short, replace(log, meta={**log.meta, "cut_short": why}))
    out = tmp_path / "fits" / "system" / "lab3.yaml"
    out.parent.mkdir(parents=True)
    out.write_text("# someone's config\n")
    friction = ["fit.payload=false", "fit.payload_pos=false", "fit.armature=false"]  # 3 s of logs fit no more
    args = [*FAST_FIT, *friction, f"logs=[{short}.npz]", f"out={out}"]
    line = _one_error_line(
        capsys, lambda: run_identify(make_cfg("identify", args), tmp_path / "r1"), "pinnmpc.identify"
    )
    assert f"out={out}: the file exists; expected a new path, or overwrite=true to replace it" in line
    assert out.read_text() == "# someone's config\n"
    result = run_identify(make_cfg("identify", [*args, "overwrite=true"]), tmp_path / "r2")
    assert load_system(out).name == "lab3" and result["warnings"] and "cut short" in result["warnings"][0]
    assert "interrupted by SIGINT" in out.read_text().split("identified_from:")[1]  # recorded in the config


def _run(args: list[str], timeout: float = 300) -> subprocess.CompletedProcess:
    """A command as a user runs it, from the project root."""
    return subprocess.run([sys.executable, "-m", *args], capture_output=True, text=True, cwd=ROOT, timeout=timeout)


def test_identify_never_writes_the_shipped_config(logs, tmp_path) -> None:
    shipped = ROOT / "conf" / "system" / "planar3.yaml"
    before = shipped.read_bytes()
    run = _run(["pinnmpc.identify", "system=planar3", f"logs=[{logs['a']}]", f"out={shipped}", "overwrite=true",
                f"hydra.run.dir={tmp_path / 'run'}"])  # fmt: skip
    lines = [line for line in run.stderr.splitlines() if line.strip()]
    assert run.returncode == 2 and lines[-1].startswith(f"pinnmpc.identify: error: out={shipped} lies inside the "
                                                        "project's conf/"), run.stderr[-2000:]  # fmt: skip
    assert shipped.read_bytes() == before


def test_collect_never_replaces_a_log(logs, tmp_path) -> None:
    run_dir = tmp_path / "run"
    write_log(run_dir / "robot_log", read_log(logs["a"], load_system("planar3")))
    before = {p.name: p.read_bytes() for p in run_dir.iterdir()}
    run = _run(["pinnmpc.collect", *TINY, "robot_time=1", f"hydra.run.dir={run_dir}"])
    lines = [line for line in run.stderr.splitlines() if line.strip()]
    assert run.returncode == 2, run.stderr[-2000:]
    expected = f"out=robot_log: {run_dir / 'robot_log.npz'} already holds a log (a collect never replaces one)"
    assert lines[-1].startswith(f"pinnmpc.collect: error: {expected}; expected a run dir without it"), lines
    assert {p.name: p.read_bytes() for p in run_dir.iterdir() if p.name in before} == before


def _start_long_collect(run_dir: Path) -> subprocess.Popen:
    """A collect of far more robot time than a test waits for; its output to files in tmp."""
    args = [sys.executable, "-m", "pinnmpc.collect", *TINY, "robot_time=600", f"hydra.run.dir={run_dir}"]
    with open(run_dir.parent / "collect.out", "w") as out, open(run_dir.parent / "collect.err", "w") as err:
        return subprocess.Popen(args, cwd=ROOT, stdout=out, stderr=err, text=True)  # the child keeps its own copies


def _wait_for_log(proc: subprocess.Popen, log: Path, timeout: float = 300) -> None:
    """Poll until the collect has written its first episode (the process still running)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.poll() is None and not log.exists():
        time.sleep(0.05)
    assert proc.poll() is None and log.exists(), f"the collect ended (rc {proc.poll()}) or never wrote {log}"


def test_a_killed_collect_keeps_its_finished_episodes(make_cfg, tmp_path) -> None:
    run_dir = tmp_path / "run"
    proc = _start_long_collect(run_dir)
    try:
        _wait_for_log(proc, run_dir / "robot_log.npz")
    finally:
        proc.kill()
        proc.wait(timeout=60)
    assert proc.returncode == -signal.SIGKILL
    system = load_system("planar3")
    log = read_log(run_dir / "robot_log.npz", system)  # whole: written atomically
    assert log.meta["cut_short"].startswith("the collect did not finish (killed?): ")
    assert len(log.episodes) >= 1 and 0 < log.robot_time < 600
    # exactly the episodes an uninterrupted collect of that much robot time logs
    whole = collect(make_cfg("collect", [*TINY, f"robot_time={log.robot_time}"]), system, None, None)
    for key in ("t", "x", "u", "episode", "t_fine", "x_fine", "episode_fine"):
        np.testing.assert_array_equal(getattr(log, key), getattr(whole, key), err_msg=key)


def test_a_stopped_collect_says_it_was_cut_short(tmp_path) -> None:
    run_dir = tmp_path / "run"
    proc = _start_long_collect(run_dir)
    try:
        _wait_for_log(proc, run_dir / "robot_log.npz")
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    out = (tmp_path / "collect.out").read_text().splitlines()
    assert proc.returncode == 130, (tmp_path / "collect.err").read_text()[-2000:]
    assert out[-1].startswith("collect cut short (interrupted by SIGINT: ") and "of 600 s of robot time" in out[-1]
    system = load_system("planar3")
    for name in ("robot_log.npz", "robot_log.csv"):
        log = read_log(run_dir / name, system)
        assert log.meta["cut_short"].startswith("interrupted by SIGINT: ") and log.t_fine is not None
