"""The robot log format: round trips, every refusal in one line naming the file, and the transitions it yields."""

from __future__ import annotations

import json
from contextlib import nullcontext
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from pinnmpc.robot_data.episodes import check_enough, split_episodes, transitions, transitions_per_second
from pinnmpc.robot_data.logs import RobotLog, read_log, write_log
from pinnmpc.systems.base import Box

TAU, FINE = 0.1, 4
ARM = SimpleNamespace(  # what read_log asks of a system
    name="arm2",
    tau=TAU,
    state_names=("q_a", "q_b", "v_a", "v_b"),
    input_names=("u_a", "u_b"),
    input_box=Box((-2.0, -1.0), (2.0, 1.0)),
)


def synthetic(lengths: tuple[int, ...] = (5, 3), fine: int = FINE) -> RobotLog:
    """Episodes of x(t) = known smooth functions, the input a different constant per period."""
    ts, xs, us, es, tf, xf, ef = [], [], [], [], [], [], []
    t0, rng = 0.0, np.random.default_rng(1)
    state = lambda t: np.stack([np.sin(t), np.cos(t), t, t**2], axis=-1)  # noqa: E731
    for e, n in enumerate(lengths):
        t = t0 + TAU * np.arange(n)
        u = rng.uniform(-1, 1, (n, 2)) * [2.0, 1.0]
        u[-1] = u[-2]
        tfine = t0 + TAU / fine * np.arange((n - 1) * fine + 1)
        tfine[::fine] = t  # the same numbers at the control times
        ts.append(t), xs.append(state(t)), us.append(u), es.append(np.full(n, 3 * e))
        tf.append(tfine), xf.append(state(tfine)), ef.append(np.full(len(tfine), 3 * e))
        t0 = t[-1] + 1.0
    meta = {
        "system": "arm2",
        "tau": TAU,
        "state_names": list(ARM.state_names),
        "input_names": list(ARM.input_names),
        "fine": fine,
        "seed": 0,
    }
    cat = np.concatenate
    return RobotLog(cat(ts), cat(xs), cat(us), cat(es), cat(tf), cat(xf), cat(ef), meta)


def same(a: RobotLog, b: RobotLog) -> None:
    """Every array and the meta equal, exactly."""
    for key in ("t", "x", "u", "episode", "t_fine", "x_fine", "episode_fine"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key), err_msg=key)
    assert a.meta == b.meta


def test_round_trip_npz_and_csv(tmp_path: Path) -> None:
    log = synthetic()
    written = write_log(tmp_path / "log", log)
    assert sorted(p.name for p in written) == ["log.csv", "log.npz", "log_fine.csv"]
    assert (tmp_path / "log.csv").read_text().startswith("# meta: {")
    same(read_log(tmp_path / "log.npz", ARM), log)
    same(read_log(tmp_path / "log.csv", ARM), log)
    (tmp_path / "log_fine.csv").unlink()  # the meta promises a fine part: read at the control rate, 4x coarser
    with pytest.raises(ValueError, match=r"log\.csv: meta fine=4 but log_fine\.csv is missing; expected it beside"):
        read_log(tmp_path / "log.csv", ARM)
    write_log(
        tmp_path / "bare", replace(log, t_fine=None, x_fine=None, episode_fine=None, meta={**log.meta, "fine": 1})
    )
    bare = read_log(tmp_path / "bare.csv", ARM)
    assert bare.t_fine is None and bare.fine == 1
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary left


def test_a_robots_reported_commands_round_trip_and_follow_a_split(tmp_path: Path) -> None:
    """The command a robot reported at each fine sample (plant=franka: libfranka's dq_d) is kept by the .npz and the
    fine CSV (`<input>_reported` columns), travels with the episodes a split keeps, and a wrong shape is refused."""
    from pinnmpc.robot_data.episodes import select_episodes

    log = synthetic()
    log = replace(log, command_fine=log.u_fine() + 0.01 * np.sin(log.t_fine)[:, None])
    write_log(tmp_path / "log", log)
    assert "u_b_reported" in (tmp_path / "log_fine.csv").read_text().splitlines()[1]
    for suffix in (".npz", ".csv"):
        back = read_log(tmp_path / f"log{suffix}", ARM)
        same(back, log)
        np.testing.assert_array_equal(back.command_fine, log.command_fine)
    np.testing.assert_array_equal(log.u_fine()[log.episode_fine == 3][::FINE], log.u[log.episode == 3])
    part = select_episodes(log, [3])
    np.testing.assert_array_equal(part.command_fine, log.command_fine[log.episode_fine == 3])
    with pytest.raises(ValueError, match=r"reported commands of shape \(10, 2\)"):
        write_log(tmp_path / "bad", replace(log, command_fine=log.command_fine[:10]))


def test_write_failure_leaves_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import pinnmpc.robot_data.logs as logs

    calls = []

    def fail_second(path: Path, write: object) -> None:
        calls.append(path)
        if len(calls) == 2:
            raise OSError("disk full")
        Path(path).write_text("x")

    monkeypatch.setattr(logs, "atomic_write", fail_second)
    with pytest.raises(OSError):
        write_log(tmp_path / "log", synthetic())
    assert list(tmp_path.iterdir()) == []


def bad_cases() -> dict[str, tuple[RobotLog, str]]:
    """Each broken log and a piece of the message it must give."""
    log = synthetic()
    x_nan, t_back, t_gap, u_out, ep_neg, ep_frac = (log.x.copy(), log.t.copy(), log.t.copy(), log.u.copy(),
                                                    log.episode.copy(), log.episode.astype(float))  # fmt: skip
    x_nan[2, 1] = np.nan
    t_back[6] = t_back[5] - 0.5
    t_gap[3:5] += 0.05
    u_out[1, 0] = 2.0 + 1e-6
    ep_neg[:5] = -1
    ep_frac[:5] = 0.5
    other = dict(log.meta, system="other")
    names = dict(log.meta, state_names=["a", "b", "c", "d"])
    return {
        "system": (replace(log, meta=other), "system 'other'; expected 'arm2'"),
        "names": (replace(log, meta=names), "state_names"),
        "tau": (replace(log, meta=dict(log.meta, tau=0.2)), "tau=0.2; expected the system's tau=0.1"),
        "nan": (replace(log, x=x_nan), "non-finite"),
        "backwards": (replace(log, t=t_back, t_fine=None, x_fine=None, episode_fine=None), "time goes backwards"),
        "gap": (replace(log, t=t_gap, t_fine=None, x_fine=None, episode_fine=None), "gap of"),
        "box": (replace(log, u=u_out), "outside the input box"),
        "negative": (replace(log, episode=ep_neg), "expected integers >= 0"),
        "fractional": (replace(log, episode=ep_frac), "expected integers >= 0"),
        "lengths": (replace(log, u=log.u[:-1]), "array shapes"),
        "fine": (replace(log, x_fine=log.x_fine + 1e-3), "differ from the control-rate samples"),
    }


@pytest.mark.parametrize("case", list(bad_cases()))
@pytest.mark.parametrize("suffix", [".npz", ".csv"])
def test_bad_logs_refused_in_one_line(tmp_path: Path, case: str, suffix: str, monkeypatch: pytest.MonkeyPatch) -> None:
    import pinnmpc.robot_data.logs as logs

    log, expected = bad_cases()[case]
    stem = tmp_path / "bad"
    arrays = {"t": log.t, "x": log.x, "u": log.u, "episode": log.episode, "meta": np.array(json.dumps(log.meta))}
    if log.t_fine is not None:
        arrays.update(t_fine=log.t_fine, x_fine=log.x_fine, episode_fine=log.episode_fine)
    if suffix == ".npz":
        np.savez(stem.with_suffix(".npz"), **arrays)
    else:
        with pytest.raises(ValueError) if case not in ("system", "names", "box") else nullcontext() as caught:
            write_log(stem, log)  # the writer refuses what needs no system; the reader must refuse it as well
        if case == "lengths":  # a CSV has rows: a short one is what mismatched lengths look like there
            write_log(stem, synthetic())
            lines = stem.with_suffix(".csv").read_text().splitlines()
            lines[-1] = lines[-1].rsplit(",", 1)[0]
            stem.with_suffix(".csv").write_text("\n".join(lines) + "\n")
            expected = "has 7 cells; expected 8"
        elif caught is not None:
            assert "\n" not in str(caught.value) and str(stem) in str(caught.value)
            monkeypatch.setattr(logs, "_check", lambda *a: None)
            write_log(stem, log)
            monkeypatch.undo()
    with pytest.raises(ValueError) as info:
        read_log(stem.with_suffix(suffix), ARM)
    message = str(info.value)
    assert "\n" not in message and f"bad{suffix}" in message and expected in message, message


def test_missing_file_and_spacing(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"nope\.npz: no such file"):
        read_log(tmp_path / "nope.npz", ARM)
    log = synthetic(fine=1)
    log = replace(log, t=log.t * 2.0, t_fine=None, x_fine=None, episode_fine=None)
    np.savez(tmp_path / "slow.npz", t=log.t, x=log.x, u=log.u, episode=log.episode)
    with pytest.raises(ValueError, match=r"slow\.npz: samples 0\.2 s apart; expected the control period's 0\.1 s"):
        read_log(tmp_path / "slow.npz", ARM)


def test_transitions_count_and_values() -> None:
    log = synthetic((5, 3))
    periods = 4 + 2
    t, x0, u, xt = transitions([log], t_max=TAU)
    assert len(t) == periods * (FINE + 1) * FINE // 2  # every pair of the FINE + 1 samples of each period
    assert t.dtype == x0.dtype == u.dtype == xt.dtype == __import__("torch").float64
    assert t.shape == (len(t), 1) and x0.shape == (len(t), 4) and u.shape == (len(t), 2)
    t0 = np.arcsin(x0[:, 0].numpy())  # the synthetic state: q_a = sin(time) and v_a = time
    np.testing.assert_allclose(xt[:, 2] - x0[:, 2], t[:, 0], atol=1e-12)  # t = t_j - t_i
    assert np.isfinite(t0).all() and t.max() <= TAU + 1e-12 and t.min() > 0
    # the input is that of the period both samples lie in: never a pair across a period boundary
    k = np.floor((x0[:, 2].numpy() - log.t[log.episode == log.episode[0]][0]) / TAU + 1e-9)
    period_of = {(int(e), float(tk)) for e, tk in zip(log.episode, log.t)}
    assert period_of and k.min() >= 0
    for ti, ui, tj in zip(x0[:, 2].numpy(), u.numpy(), xt[:, 2].numpy()):
        row = int(np.searchsorted(log.t, ti + 1e-9) - 1)
        assert log.t[row] <= ti + 1e-12 and tj <= log.t[row] + TAU + 1e-12
        np.testing.assert_array_equal(ui, log.u[row])
    short, *_ = transitions([log], t_max=TAU / FINE)
    assert len(short) == periods * FINE
    control, *_ = transitions([replace(log, t_fine=None, x_fine=None, episode_fine=None)], t_max=TAU)
    assert len(control) == periods
    assert transitions_per_second(TAU, FINE, TAU) * TAU == (FINE + 1) * FINE // 2


def test_split_and_enough() -> None:
    log = synthetic((5, 3, 4, 2))
    train, val = split_episodes(log, 0.25, seed=0)
    assert len(val.episodes) == 1 and len(train.episodes) == 3
    assert not set(train.episodes) & set(val.episodes)
    assert len(train.t) + len(val.t) == len(log.t) and len(train.t_fine) + len(val.t_fine) == len(log.t_fine)
    check_enough(10, 10, "x")
    with pytest.raises(ValueError) as info:
        check_enough(120, 2000, "data.logs", tau=0.1, fine=10, t_max=0.1)
    assert str(info.value) == (
        "data.logs hold 120 transitions; expected at least 2000 (about 3.64 s of robot time at tau=0.1 with fine=10)"
    )


def test_a_short_collect_run_writes_a_log_read_log_accepts(make_cfg, tmp_path: Path) -> None:
    """6 s of the lab robot (a closed loop of the shipped NMPC on random-0), noise on the logged states."""
    pytest.importorskip("mujoco")
    from pinnmpc import load_system
    from pinnmpc.robot_data.collect import run_collect

    cfg = make_cfg(
        "collect", ["system=planar3", "plant.robot=lab", "robot_time=6", "noise_sigma=1e-4", "progress=false"]
    )
    result = run_collect(cfg, tmp_path)
    assert result["robot_time_s"] == pytest.approx(6.0) and result["samples"] == 61 and result["fine_samples"] == 601
    system = load_system("planar3")
    for suffix in (".npz", ".csv"):
        log = read_log(tmp_path / f"robot_log{suffix}", system)
        assert log.meta["robot"] == "lab" and log.meta["fine"] == 10 and log.meta["noise_sigma"] == 1e-4
        assert log.robot_time == pytest.approx(6.0) and log.t_fine is not None
    t, *_ = transitions([log], t_max=system.tau)
    assert len(t) == 60 * 55


def test_collect_with_an_unknown_robot_exits_2_in_one_line(tmp_path: Path) -> None:
    import subprocess
    import sys

    run = subprocess.run(
        [sys.executable, "-m", "pinnmpc.collect", "system=planar3", "plant.robot=nope", f"hydra.run.dir={tmp_path}/r"],
        capture_output=True,
        text=True,
        cwd=Path(__file__).resolve().parents[1],
        timeout=300,
    )
    assert run.returncode == 2, run.stderr
    lines = [line for line in run.stderr.splitlines() if line.strip()]
    said = "pinnmpc.collect: error: plant.robot='nope'; expected null or one of ['lab', 'shop']"
    assert lines[-1].startswith(said), lines


def test_pairs_from_a_command_delay_begin_that_far_into_each_period() -> None:
    """start_at (model.command_delay): only pairs from the sample that far into its period, the input still the
    period's; a delay off the fine samples is refused in one line."""
    log = synthetic((5, 3))
    h = TAU / FINE
    t, x0, u, xt = transitions([log], t_max=TAU, start_at=2 * h)
    assert len(t) == (4 + 2) * (FINE - 2)  # from that sample to each later one of the period
    into = np.array([(ti - log.t[np.searchsorted(log.t, ti + 1e-9) - 1]) for ti in x0[:, 2].numpy()])
    np.testing.assert_allclose(into, 2 * h, atol=1e-12)
    whole, *_ = transitions([log], t_max=TAU - 2 * h, start_at=2 * h)
    assert float(whole.max()) == pytest.approx(TAU - 2 * h)
    with pytest.raises(ValueError, match=r"pairs from 0.0003 s into each period \(model.command_delay\)"):
        transitions([log], t_max=TAU, start_at=0.0003)
