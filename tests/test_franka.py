"""plant=franka with the real parts: franky-sim served on a loopback address of its own, libfranka through franky,
closed loops of every controller kind, the safety layer, the watchdog, SIGINT mid-motion."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from pinnmpc.plant.franka_sim import SimServer, franky_missing

pytestmark = pytest.mark.skipif(bool(franky_missing()), reason=franky_missing() or "franky present")

ROOT = Path(__file__).resolve().parents[1]
FR3_GAINS = [450.0, 450.0, 350.0, 350.0, 100.0, 100.0, 50.0]
FR3_HOME = [0.0, 0.0, 0.0, -1.5, 0.0, 1.5, 0.0]


def own_loopback(offset: int) -> str:
    """A loopback address per xdist worker and use: servers on fixed ports never meet."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
    return f"127.0.0.{10 + 20 * offset + int(worker.removeprefix('gw') or 0)}"


def pid_alive(pid: int) -> bool:
    """Whether a process of that id still runs (a zombie counts as gone)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split()[2] != "Z"
    except FileNotFoundError:
        return False


@pytest.fixture(scope="module")
def sim_host(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A real franky-sim (MuJoCo FR3) on this worker's own loopback address, stopped by its pid afterwards."""
    host = own_loopback(0)
    server = SimServer(host, FR3_GAINS, FR3_HOME, tmp_path_factory.mktemp("sim") / "franky_sim.log")
    try:
        server.wait_ready(120.0)
        yield host
    finally:
        server.stop()
    assert not pid_alive(server.pid)


@pytest.mark.parametrize("controller", ["nmpc", "exact", "casadi"])
def test_each_controller_kind_closes_the_loop_through_libfranka(
    sim_host: str, controller: str, make_cfg, tmp_path: Path
) -> None:
    from pinnmpc.simulation.run import run_closed_loop

    overrides = ["system=fr3", "plant=franka", "plant.simulator=none", f"plant.host={sim_host}"]
    cfg = make_cfg("closed_loop", [*overrides, f"controller={controller}", "max_steps=12", "progress=false"])
    m = run_closed_loop(cfg, tmp_path)
    assert m["status"] == "ok", m["status"]
    assert m["franka"]["errors"] == [] and m["franka"]["at_rest"]
    assert m["steps"] == 12 and m["joint_limit_samples"] == 0
    assert abs(m["franka"]["robot_period_s"]["median"] - 0.05) <= 1.5e-3  # the robot's clock, not the wall's
    assert max(m["mae"][f"q_joint{j}"] for j in range(1, 8)) < 5e-3


def test_commands_go_out_at_a_fixed_robot_time_after_their_state(sim_host: str, make_cfg, tmp_path: Path) -> None:
    """plant.command_at: each command waits on the robot's clock until that long after the state it answers (a
    dead time the same in every period); metrics.json says when they went out."""
    from pinnmpc.simulation.run import run_closed_loop

    overrides = ["system=fr3", "plant=franka", "plant.simulator=none", f"plant.host={sim_host}"]
    overrides.append("plant.command_at=0.03")
    m = run_closed_loop(make_cfg("closed_loop", [*overrides, "max_steps=8", "progress=false"]), tmp_path)
    assert m["status"] == "ok" and m["franka"]["errors"] == [], m["status"]
    offset, late = m["franka"]["command_offset_s"], m["franka"]["late_commands"]
    assert 0.0295 <= offset["median"] <= 0.032, offset  # within its ticks (plant.franka.LATE_TICKS)
    # a command the controller answered later than that (a loaded machine) goes out at once and is counted as late
    assert offset["max"] <= 0.032 or late >= 1, (offset, late)


def test_commands_a_whole_period_late_are_planned_for(sim_host: str, make_cfg, tmp_path: Path) -> None:
    """plant.command_at = tau: each command goes out as the next period begins, whatever the controller's time, and
    the controller plans from its model's prediction of that period's start."""
    from pinnmpc.simulation.run import run_closed_loop

    overrides = ["system=fr3", "plant=franka", "plant.simulator=none", f"plant.host={sim_host}", "controller=casadi"]
    overrides += ["plant.command_at=0.05", "max_steps=12", "progress=false"]
    m = run_closed_loop(make_cfg("closed_loop", overrides), tmp_path)
    assert m["status"] == "ok" and m["franka"]["errors"] == [], m["status"]
    assert 0.0495 <= m["franka"]["command_offset_s"]["median"] <= 0.0515, m["franka"]["command_offset_s"]
    assert max(m["mae"][f"q_joint{j}"] for j in range(1, 8)) < 5e-3


def test_a_state_read_a_tick_late_is_carried_back_to_its_time() -> None:
    """state_at: from reads 1 ms either side of the target on a smooth motion (q = sin t per joint) the state at the
    target (q to 1e-9); from the late read alone to its acceleration's half a tick squared; the raw late read is a
    tick's travel off."""
    from pinnmpc.plant.franka import state_at

    target, nq = 1.3, 2
    at = lambda t: np.r_[np.sin([t, 2 * t]), np.cos([t, 2 * t]) * [1.0, 2.0]]  # noqa: E731
    before, after = (target - 1e-3, at(target - 1e-3)), (target + 1e-3, at(target + 1e-3))
    got = state_at(target, before, after, nq)
    np.testing.assert_allclose(got[:nq], at(target)[:nq], atol=1e-9)  # q
    np.testing.assert_allclose(got[nq:], at(target)[nq:], atol=8 * 0.5e-6)  # v, linear: |v''| <= 8 here
    alone = state_at(target, None, after, nq)
    assert np.abs(alone[:nq] - at(target)[:nq]).max() < 4.0 * 0.5e-6  # |q''| <= 4 here
    assert np.abs(after[1][:nq] - at(target)[:nq]).max() > 1e-3  # the raw read: v x 1 ms


def test_the_safety_layer_slows_before_the_limits_and_clips_the_speed() -> None:
    from pinnmpc.plant.franka_safety import SafetyLayer
    from pinnmpc.plant.settings import FrankaPlantSettings
    from pinnmpc.systems import load_system

    fr3 = load_system("fr3")
    layer = SafetyLayer(fr3, fr3.tau, FrankaPlantSettings())
    high = np.array(fr3.joint_limits.high)
    x = np.concatenate([np.array(FR3_HOME), np.zeros(7)])
    free = layer.command(np.full(7, 0.5), x)
    assert np.allclose(free, 0.5) and layer.events["slowed_commands"] == 0
    layer.events["slowed_commands"] = 0
    fast = layer.command(np.full(7, 50.0), x)
    up, _ = layer.allowed(x[:7])
    assert np.allclose(fast, np.minimum(layer.vmax, up)) and layer.events["clipped_commands"] == 1
    near = x.copy()
    near[:7] = high - 0.06  # 1 cm of room before the margin
    slowed = layer.command(np.full(7, 2.0), near)
    assert np.all(slowed * fr3.tau <= 0.01 + 1e-12) and np.all(slowed > 0)
    past = near.copy()
    past[:7] = high - 0.01  # inside the margin: only away from the limit
    assert np.all(layer.command(np.full(7, 1.0), past) == 0.0)
    assert np.allclose(layer.command(np.full(7, -1.0), past), -1.0)
    nan = layer.command(np.full(7, np.nan), x)
    assert np.all(nan == 0.0) and layer.events["non_finite_commands"] == 1


def test_the_watchdog_stops_the_arm_when_the_controller_misses_its_period(sim_host: str) -> None:
    from pinnmpc.plant.base import PlantError
    from pinnmpc.plant.franka import FrankaPlant
    from pinnmpc.plant.settings import FrankaPlantSettings
    from pinnmpc.systems import load_system

    fr3 = load_system("fr3")
    plant = FrankaPlant(fr3, fr3.tau, FrankaPlantSettings(simulator="none", host=sim_host))
    try:
        x = plant.start(np.concatenate([np.array(FR3_HOME), np.zeros(7)]))
        x = plant.step(x, np.full(7, 0.2))
        late = plant.period_start + 1.5 * fr3.tau
        while plant.now() < late:  # the controller "thinks" past its period (robot time, not wall time)
            time.sleep(0.005)
        with pytest.raises(PlantError, match="watchdog"):
            plant.step(x, np.full(7, 0.2))
        assert plant.safety.events["watchdog_stops"] == 1 and plant.at_rest()
    finally:
        plant.close()
    assert plant.report()["errors"] == []


def test_the_loop_starts_with_the_arm_settled_on_the_references_start(sim_host: str) -> None:
    """franky's move to the start ends while franky-sim's servo still closes in (mrad off, cm/s): the plant waits on
    the robot's clock until every joint is slower than plant.start_settle_speed, so the loop starts where it should."""
    from pinnmpc.plant.franka import FrankaPlant
    from pinnmpc.plant.settings import FrankaPlantSettings
    from pinnmpc.systems import load_system

    fr3 = load_system("fr3")
    settings = FrankaPlantSettings(simulator="none", host=sim_host)
    plant = FrankaPlant(fr3, fr3.tau, settings)
    target = np.array(FR3_HOME) + np.array([0.0, 0.2, 0.0, 0.3, 0.0, -0.3, 0.0])
    try:
        for q0 in (target, np.array(FR3_HOME)):
            x = plant.start(np.concatenate([q0, np.zeros(7)]))
            assert np.abs(x[7:]).max() <= settings.start_settle_speed and np.abs(x[:7] - q0).max() < 3e-4
    finally:
        plant.close()
    assert plant.report()["errors"] == []


def test_a_target_outside_the_limits_is_refused_before_the_arm_moves(sim_host: str) -> None:
    from pinnmpc.plant.base import PlantError
    from pinnmpc.plant.franka import FrankaPlant
    from pinnmpc.plant.settings import FrankaPlantSettings
    from pinnmpc.systems import load_system

    fr3 = load_system("fr3")
    plant = FrankaPlant(fr3, fr3.tau, FrankaPlantSettings(simulator="none", host=sim_host))
    try:
        before = plant.measure()[1]
        bad = before.copy()
        bad[3] = 0.0  # joint 4 lives below -0.1169 rad
        with pytest.raises(PlantError, match="joint 4 target"):
            plant.start(bad)
        assert np.abs(plant.measure()[1][:7] - before[:7]).max() < 1e-3
    finally:
        plant.close()


def test_a_velocity_limit_above_the_robots_is_refused_at_connect(sim_host: str) -> None:
    from pinnmpc.plant.base import PlantError
    from pinnmpc.plant.franka import FrankaPlant
    from pinnmpc.plant.settings import FrankaPlantSettings
    from pinnmpc.systems import load_system

    fr3 = load_system("fr3")
    settings = FrankaPlantSettings(simulator="none", host=sim_host, velocity_limit=[2.62] * 7)
    with pytest.raises(PlantError, match=r"plant.velocity_limit=\[2.62, .*above the robot's joint velocity limits"):
        FrankaPlant(fr3, fr3.tau, settings)


def test_every_controller_box_is_narrowed_to_the_robots_velocity_limits(make_cfg) -> None:
    """The FR3 URDF's velocity limits (2.62-5.26 rad/s) lie above franky's (2.175, 2.61): no plan may count on a
    command the safety layer would clip; a limit of the wrong length is one line."""
    from pinnmpc.simulation.settings import within_plant_limits
    from pinnmpc.systems import load_system
    from pinnmpc.util.checks import SettingError

    fr3 = load_system("fr3")
    cfg = make_cfg("closed_loop", ["system=fr3", "plant=franka", "controller=casadi"])
    within_plant_limits(cfg, fr3)
    assert list(cfg.controller.u_high) == [2.175] * 4 + [2.61] * 3 == [-v for v in cfg.controller.u_low]
    cfg = make_cfg("closed_loop", ["system=fr3", "plant=franka", "controller.u_high=[1,1,1,1,1,1,1]"])
    within_plant_limits(cfg, fr3)
    assert list(cfg.controller.u_high) == [1.0] * 7  # tighter bounds of the user's stay
    cfg = make_cfg("closed_loop", ["system=fr3", "plant=franka", "plant.velocity_limit=[2.0,2.0]"])
    with pytest.raises(SettingError, match=r"plant.velocity_limit=\[2.0, 2.0\]: expected 7 positive speeds"):
        within_plant_limits(cfg, fr3)


def test_bad_franka_settings_are_one_line_each() -> None:
    from pinnmpc.plant.settings import plant_settings

    with pytest.raises(ValueError, match=r"plant.host=None: expected the robot's address with plant.simulator=none"):
        plant_settings({"kind": "franka", "simulator": "none"}).make_consistent()
    with pytest.raises(ValueError, match=r"plant.simulator='genesis'"):
        plant_settings({"kind": "franka", "simulator": "genesis"})
    with pytest.raises(ValueError, match=r"plant.friction_scale=1.2"):
        plant_settings({"kind": "franka", "friction_scale": 1.2})


def test_the_embedded_robot_ends_at_rest_and_leaves_no_server_after_sigint(tmp_path: Path) -> None:
    host = own_loopback(1)
    run_dir = tmp_path / "run"
    cmd = [sys.executable, "-m", "pinnmpc.closed_loop", "system=fr3", "plant=franka", f"plant.host={host}"]
    cmd += ["controller=casadi", "progress=true", f"hydra.run.dir={run_dir}"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    seen = ""
    try:
        while not re.search(r"closed loop: .*\| *([5-9]|\d\d+)/\d+", seen[-200:]):  # a few steps into the motion
            chunk = proc.stdout.read(1) if proc.stdout else ""
            if not chunk:
                break
            seen += chunk
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
    out = seen + rest
    assert proc.returncode != 0 and "interrupted by SIGINT" in out, out[-2000:]
    m = json.loads((run_dir / "metrics.json").read_text())
    assert m["status"] == "interrupted" and m["franka"]["at_rest"] and m["franka"]["errors"] == []
    assert not pid_alive(m["franka"]["server_pid"])


def test_collect_logs_the_robot_stream_through_libfranka(sim_host: str, tmp_path: Path) -> None:
    from pinnmpc.robot_data.logs import read_logs
    from pinnmpc.systems import load_system

    run_dir = tmp_path / "collect"
    cmd = [sys.executable, "-m", "pinnmpc.collect", "system=fr3", "plant=franka", "plant.simulator=none"]
    cmd += [f"plant.host={sim_host}", "robot_time=2", "episodes.kinds=[excitation,random]", "excitation.duration=1"]
    r = subprocess.run([*cmd, "progress=false", f"hydra.run.dir={run_dir}"], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    (log,) = read_logs([str(run_dir / "robot_log.npz")], load_system("fr3"))
    assert log.meta["robot"] == f"franka@{sim_host}" and log.meta["fine"] == 10
    assert sorted(set(log.episode.tolist())) == [0, 1] and len(log.x) == 42 and len(log.x_fine) == 402
    for e in (0, 1):
        x, xf = log.x[log.episode == e], log.x_fine[log.episode_fine == e]
        assert np.array_equal(x, xf[:: log.meta["fine"]])  # the control rate is the fine samples' period ends
        dq = np.diff(xf[:, :7], axis=0) / (0.05 / 10)  # each fine step moves as its mean velocity says (a state
        #   read a tick late misses it by 0.1-0.3 rad/s; the first step, from rest under the full jerk, by up to 0.04)
        assert np.abs(dq - 0.5 * (xf[1:, 7:] + xf[:-1, 7:]))[1:].max() < 0.05
    ramp = np.asarray(log.meta["command_acceleration"])  # franky's ramp, which identify leaves out of the fit
    np.testing.assert_allclose(ramp, [15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0])  # the Panda's limits, factor 1
    u = log.u[log.episode == 0][:-1]  # the excitation: no command further from the last than half a period's ramp
    assert np.all(np.abs(np.diff(np.vstack((np.zeros(7), u)), axis=0)) <= 0.5 * 0.05 * ramp + 1e-12)
    # the command the robot reported at each fine sample (libfranka's dq_d): zero at each start; 5 ms into a period
    # whose input stepped, still short of it (franky's ramp); by nearly every period's end settled on the input logged
    # for it, the command as the safety layer sent it (logging the excitation's own wrist command of 2.63 rad/s where
    # franky takes 2.61 settled on 75 %)
    held, stepped = log.u_fine(), 0
    assert log.command_fine is not None and log.command_fine.shape == log.x_fine.shape[:1] + (7,)
    for e in (0, 1):
        cf, hf = log.command_fine[log.episode_fine == e], held[log.episode_fine == e]
        assert np.abs(cf[0]).max() < 1e-6
        step = np.abs(hf[10:-1:10] - hf[:-11:10])  # each period's input against the one before
        short = np.abs(cf[11::10] - hf[10:-1:10])  # 5 ms into the period
        assert np.all(short[step > 0.05] > 0.1 * step[step > 0.05])
        stepped += int(np.count_nonzero(step > 0.05))
        settled = np.abs(cf[10::10] - hf[:-1:10]).max(axis=1) < 2e-3
        assert settled.mean() >= 0.9
    assert stepped > 10


def franka_sim_children() -> list[int]:
    """The franky-sim servers this process started that still run."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
            cmdline = (stat.parent / "cmdline").read_bytes()
        except (FileNotFoundError, ProcessLookupError, IndexError):
            continue
        if int(fields[1]) == os.getpid() and fields[0] != "Z" and b"pinnmpc.plant.franka_sim" in cmdline:
            found.append(int(stat.parent.name))
    return found


def test_collect_with_an_embedded_robot_leaves_no_server_and_logs_the_inputs_held(make_cfg, tmp_path: Path) -> None:
    """The collect's settings check starts no robot of its own; with plant.command_at = tau each logged input is the
    one that drove its period (the first: the arm at rest)."""
    from pinnmpc.robot_data.collect import run_collect
    from pinnmpc.robot_data.logs import read_logs
    from pinnmpc.systems import load_system

    overrides = ["system=fr3", "plant=franka", f"plant.host={own_loopback(2)}", "plant.command_at=0.05"]
    overrides += ["robot_time=2.5", "episodes.kinds=[excitation,random]", "excitation.duration=1", "progress=false"]
    before = set(franka_sim_children())
    run_collect(make_cfg("collect", overrides), tmp_path)
    assert set(franka_sim_children()) <= before
    (log,) = read_logs([str(tmp_path / "robot_log.npz")], load_system("fr3"))
    assert log.meta["command_at"] == 0.05 and sorted(set(log.episode.tolist())) == [0, 1]
    for e in (0, 1):
        x, u = log.x[log.episode == e], log.u[log.episode == e][:-1]
        assert np.all(u[0] == 0.0) and np.abs(u[1:]).max() > 0  # the first period ran at rest
        assert np.abs(x[1:, 7:] - u).mean() < 0.02  # the servo follows the input logged for its period


def test_identify_by_the_reported_command_finds_franky_sims_arm(sim_host: str, tmp_path: Path) -> None:
    """4 s of excitation logged at 1 ms through libfranka: identify driven by the command the robot reported (the
    servo's tick law), the hand a load the servo compensates, finds franky-sim's MJCF within 20 % (armature 0.195 on
    joints 1-4 and 0.074 on the wrist, the hand 0.73 kg) and its friction at 0.5 rad/s within 10 % (frictionloss
    1.137 x4, 0.763, 0.44, 0.248 N m, damping 0.21); driven by the held input franky's ramp stays in the residual."""
    from pinnmpc.robot_data.identify import identify
    from pinnmpc.robot_data.logs import read_logs
    from pinnmpc.systems import load_system
    from pinnmpc.systems.urdf import Payload

    run_dir = tmp_path / "collect"
    cmd = [sys.executable, "-m", "pinnmpc.collect", "system=fr3", "plant=franka", "plant.simulator=none"]
    cmd += [f"plant.host={sim_host}", "robot_time=4", "fine=50", "episodes.kinds=[excitation]"]
    cmd += ["excitation.duration=4", "progress=false", f"hydra.run.dir={run_dir}"]
    r = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    import dataclasses

    system = dataclasses.replace(load_system("fr3"), coulomb_slope=200.0)
    logs = read_logs([str(run_dir / "robot_log.npz")], system)
    hand = Payload(0.0, (-0.01, 0.0, 0.03), "link8")
    keys = ["armature", "viscous", "coulomb", "load"]
    fit = identify(system, logs, keys, load=hand, command="reported", validation_periods=0, max_samples=None)
    np.testing.assert_allclose(fit.values["armature"], [0.195] * 4 + [0.074] * 3, rtol=0.2)
    at = np.asarray(fit.values["coulomb"]) + 0.5 * np.asarray(fit.values["viscous"])  # friction at 0.5 rad/s
    np.testing.assert_allclose(at, np.array([1.137] * 4 + [0.763, 0.44, 0.248]) + 0.5 * 0.21, rtol=0.1)
    assert fit.values["load_mass"] == pytest.approx(0.73, rel=0.2) and fit.system.load.link == "link8"
    held = identify(system, logs, keys, load=hand, validation_periods=0, max_samples=None, settle=0.015)
    ratio = np.asarray(fit.torque_rms) / np.asarray(held.torque_rms)
    assert ratio[:4].max() < 0.5, ratio  # joints 1-4: the held input leaves franky's ramp in the residual


@pytest.mark.slow
def test_the_bench_robot_section_runs_on_the_franka_plant(sim_host: str, tmp_path: Path) -> None:
    run_dir = tmp_path / "bench"
    cmd = [sys.executable, "-m", "pinnmpc.bench", "system=fr3", "plant=franka", "plant.simulator=none"]
    cmd += [f"plant.host={sim_host}", "robot.enabled=true", "robot.references=[default]", "closed_loop.max_steps=5"]
    cmd += ["step.enabled=false", "closed_loop.enabled=false", "optimality.enabled=false", "scaling.enabled=false"]
    cmd += ["robot.paired_ocp=false", "robot.classical_variants=false", "progress=false", f"hydra.run.dir={run_dir}"]
    cmd += ["peers.enabled=false", "floor.horizons=[3]", "floor.max_steps=10", "floor.cold.enabled=false"]
    r = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    bench = json.loads((run_dir / "bench.json").read_text())
    (floor,) = bench["floor"]["rows"]  # a timing section: on the nominal model, not on the real-time robot
    worst = max(v for k, v in floor["mae"].items() if k.startswith("q_"))  # 0.2 rad when it ran on the robot
    assert bench["floor"]["plant"] == "scipy" and floor["status"] == "ok" and worst < 1e-4
    rows = bench["robot"]["rows"]
    robot_rows = [row for key, row in rows.items() if "franka" in row]
    assert len(robot_rows) == 2  # the nominal classical NMPC and the shipped network on the robot
    for row in robot_rows:
        assert row["status"] == "ok" and row["franka"]["errors"] == [] and row["franka"]["at_rest"]
        assert row["joint_limit_samples"] == 0 and "p99" in row["ocp_time_s"]
    assert f"On the robot `franka@{sim_host}`" in (run_dir / "bench.md").read_text()


def test_the_server_dies_with_the_process_that_started_it_even_by_sigkill() -> None:
    host = own_loopback(2)
    code = (
        "import sys, time\nfrom pinnmpc.plant.franka_sim import SimServer\n"
        f"s = SimServer({host!r}, {FR3_GAINS!r}, {FR3_HOME!r}, None)\nprint(s.pid, flush=True)\ntime.sleep(600)\n"
    )
    parent = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    try:
        pid = int(parent.stdout.readline()) if parent.stdout else 0
        assert pid and pid_alive(pid)
        parent.kill()
        parent.wait()
        deadline = time.monotonic() + 120  # a bound for a loaded machine only: the condition decides
        while pid_alive(pid) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not pid_alive(pid)
    finally:
        if parent.poll() is None:
            parent.kill()
