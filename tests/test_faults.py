"""Faults in the loop, survived and reported: real closed loops on planar3 with its shipped network, one fault each,
each checked for finite inputs, recovery within the stated samples and the fault named in metrics.json; and a run
whose outputs cannot be written ends with a status that says so."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from pinnmpc.plant.build import make_plant
from pinnmpc.simulation.faults import MeasurementGuard, Reading
from pinnmpc.simulation.loop import run_loop
from pinnmpc.simulation.run import run_closed_loop
from pinnmpc.simulation.setup import build_controller, system_reference
from pinnmpc.systems.registry import build_system
from tests.conftest import ROOT

BASE = ["system=planar3", "max_steps=45", "progress=false", "plots=false"]  # faults at t = 2 s: sample 20 of 45


def _run(make_cfg, tmp_path, *faults: str) -> tuple[dict, np.ndarray]:
    """One closed loop with the given fault settings: its metrics.json and the inputs the plant got."""
    m = run_closed_loop(make_cfg("closed_loop", [*BASE, *faults]), tmp_path)
    assert json.loads((tmp_path / "metrics.json").read_text())["faults"] == m["faults"]
    return m, np.load(tmp_path / "trajectory.npz")["u"]


def _one_fault(m: dict, name: str) -> dict:
    """The run's single fault record, checked for what every fault must report."""
    (f,) = m["faults"]
    assert f["fault"] == name and f["t"] == pytest.approx(2.0)
    assert f["recovered"], f  # back at its pre-fault level within faults.recovery.samples
    assert f["recovery_samples"] <= f["recovery_bound"] == 20
    assert m["status"] == "ok" and m["steps"] == 45
    return f


def test_a_nan_measurement_is_rejected_and_the_model_prediction_used(make_cfg, tmp_path):
    m, u = _run(make_cfg, tmp_path, "faults.measurement.kind=nan", "faults.measurement.state=q_joint2")
    assert np.isfinite(u).all()
    f = _one_fault(m, "measurement")
    assert "NaN on q_joint2" in f["what"] and f["actions"] == ["rejected (non-finite)"]
    assert m["measurement_guard"]["rejected_nonfinite"] == 1 and m["measurement_guard"]["rejected_jump"] == 0
    assert f["recovery_samples"] <= 2
    assert m["fallbacks"] == 0


def test_a_ten_sigma_outlier_is_rejected(make_cfg, tmp_path):
    m, u = _run(make_cfg, tmp_path, "faults.measurement.kind=outlier", "faults.measurement.sigma=0.05")
    assert np.isfinite(u).all()
    f = _one_fault(m, "measurement")
    assert "outlier of +0.5 on q_joint1" in f["what"] and f["actions"] == ["rejected (jump beyond the limit)"]
    assert m["measurement_guard"]["rejected_jump"] == 1
    assert f["recovery_samples"] <= 2


def test_a_heavier_arm_mid_run_is_absorbed(make_cfg, tmp_path):
    m, u = _run(make_cfg, tmp_path, "faults.payload.time=2.0", "faults.payload.mass_scale=1.2")
    assert np.isfinite(u).all()
    f = _one_fault(m, "payload")
    assert f["what"] == "mass_scale 1 -> 1.2" and f["error_peak"] > f["recovery_level"]  # it did knock the arm off


def test_a_payload_picked_up_by_the_mujoco_robot_is_absorbed(make_cfg, tmp_path):
    pytest.importorskip("mujoco")
    m, u = _run(make_cfg, tmp_path, "plant=mujoco", "faults.payload.time=2.0", "faults.payload.mass=0.25")
    assert np.isfinite(u).all()
    f = _one_fault(m, "payload")
    assert f["what"] == "payload 0 -> 0.25 kg"


def test_half_the_authority_of_one_joint_for_half_a_second(make_cfg, tmp_path):
    m, u = _run(make_cfg, tmp_path, "faults.authority.joint=0", "faults.authority.duration=0.5")
    assert np.isfinite(u).all()
    f = _one_fault(m, "authority")
    assert (f["onset_step"], f["end_step"]) == (20, 25) and "x 0.5" in f["what"]


def test_a_measurement_one_sample_late_is_predicted_forward(make_cfg, tmp_path):
    m, u = _run(make_cfg, tmp_path, "faults.delay.time=2.0", "faults.delay.duration=1.0")
    assert np.isfinite(u).all()
    f = _one_fault(m, "delay")
    assert f["actions"] == ["predicted forward by the model (stale)"]
    assert m["measurement_guard"]["stale_compensated"] == 10


class NaNAt:
    """A controller whose output turns non-finite at one step (everything else delegated)."""

    def __init__(self, inner, step: int) -> None:
        self.inner, self.step, self.k = inner, step, 0

    def __getattr__(self, name: str):
        return getattr(self.inner, name)

    def make_step(self, x, x_ref):
        u = self.inner.make_step(x, x_ref)
        self.k += 1
        return np.full_like(u, np.nan) if self.k - 1 == self.step else u


def test_a_non_finite_controller_output_never_reaches_the_plant(make_cfg):
    cfg = make_cfg("closed_loop", BASE)
    system = build_system(cfg.system)
    controller, domain, tau = build_controller(cfg, system)
    ref = system_reference(cfg, system, tau)
    seen = []
    plant = make_plant(system, cfg.plant, tau)
    step = plant.step
    plant.step = lambda x, u: (seen.append(np.array(u)), step(x, u))[1]  # type: ignore[method-assign]
    guard = MeasurementGuard(None)
    run = run_loop(NaNAt(controller, 5), plant, ref, max_steps=10, domain=domain, progress=False, guard=guard)
    assert np.isfinite(np.array(seen)).all() and len(seen) == 10
    assert guard.counts["inputs_held"] == 1
    np.testing.assert_array_equal(seen[5], seen[4])  # the previous input, held
    assert run.status == "ok"


def test_the_guard_rejects_a_jump_only_after_its_warmup_and_accepts_a_lasting_one():
    guard = MeasurementGuard(lambda x, u: x, warmup=3, floor=0.1, max_rejects=2)
    good = np.zeros(2)
    for k in range(3):  # residuals of 0.001: the floor sets the limit
        assert guard.screen(k, Reading(good + 0.001), good, good) is not None
    used = guard.screen(3, Reading(np.array([1.0, 0.0])), good, good)
    np.testing.assert_array_equal(used, good)  # rejected: the prediction stands in
    guard.screen(4, Reading(np.array([1.0, 0.0])), good, good)
    lasting = guard.screen(5, Reading(np.array([1.0, 0.0])), good, good)  # third in a row: the robot changed
    np.testing.assert_array_equal(lasting, [1.0, 0.0])
    assert guard.counts["rejected_jump"] == 2 and guard.counts["accepted_jump"] == 1


def test_a_misspelt_fault_setting_is_one_line_naming_it(make_cfg, tmp_path):
    with pytest.raises(ValueError, match=r"faults.measurement.kind='spike'; expected null, 'nan' or 'outlier'"):
        run_closed_loop(make_cfg("closed_loop", [*BASE, "faults.measurement.kind=spike"]), tmp_path)
    with pytest.raises(ValueError, match=r"faults.authority.joint=7; expected an index 0..2"):
        run_closed_loop(make_cfg("closed_loop", [*BASE, "faults.authority.joint=7"]), tmp_path)


def test_a_plot_that_cannot_be_written_leaves_a_status_naming_it(tmp_path):
    run_dir = tmp_path / "run"
    (run_dir / "closed_loop.png").mkdir(parents=True)  # a folder where the PNG goes
    cmd = [sys.executable, "-m", "pinnmpc.closed_loop", "max_steps=2", "progress=false", f"hydra.run.dir={run_dir}"]
    r = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert r.returncode == 1
    errors = [line for line in r.stderr.splitlines() if "error" in line.lower()]
    assert len(errors) == 1 and "Traceback" not in r.stderr
    assert f"pinnmpc.closed_loop: error: cannot write {run_dir / 'closed_loop.png'}" in errors[0]
    m = json.loads((run_dir / "metrics.json").read_text())
    assert m["status"].startswith(f"failed: cannot write {run_dir / 'closed_loop.png'}")
    assert m["followed"] is True and "tracking_bound" in m
    assert (run_dir / "trajectory.npz").is_file()
    assert m["faults"] == [] and m["measurement_guard"]["rejected_jump"] == 0  # no fault: the guard did nothing


def test_the_bench_closed_loops_take_the_same_fault_options():
    from hydra import compose, initialize_config_dir

    from pinnmpc.bench import run_controller
    from pinnmpc.bench.common import bench_reference
    from pinnmpc.surrogate import load_surrogate
    from pinnmpc.systems import PowerCube
    from tests.conftest import CONF

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("bench", ["closed_loop.max_steps=15", "progress=false", "faults.measurement.kind=nan",
                                "faults.measurement.time=1.0"])  # fmt: skip
    system = PowerCube()
    ref = bench_reference(cfg, system, 0.2, "default")
    row, _ = run_controller(cfg, system, load_surrogate(), ref, "lifted_gauss_newton", record=False)
    (f,) = row["faults"]
    assert f["fault"] == "measurement" and f["onset_step"] == 5 and f["actions"] == ["rejected (non-finite)"]
    assert row["measurement_guard"]["rejected_nonfinite"] == 1 and row["status"] == "ok"
