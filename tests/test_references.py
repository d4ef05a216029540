"""Reference trajectories: built-ins stay feasible and consistent, files round-trip, bad input fails clearly."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import scipy.io
from omegaconf import OmegaConf

from pinnmpc import load_system
from pinnmpc.cli import USER_ERRORS
from pinnmpc.references import BUILTIN_DT, Reference, ReferenceError, resample
from pinnmpc.references import builtin_reference as _builtin
from pinnmpc.references import load_reference as _load
from pinnmpc.references import read_reference as _read
from pinnmpc.references.files import check_states, out_of_box, resolve_reference_path, velocity_scale, warn_velocities
from pinnmpc.systems import system_config

CUBE = load_system("powercube")
NAMES = CUBE.state_names
SPECS = OmegaConf.to_container(system_config("powercube").references)
BUILTINS = [k for k, v in SPECS.items() if v["kind"] != "random"]
POSITIONS = (CUBE.state_box.low[:2], CUBE.state_box.high[:2])


def builtin_reference(name: str = "default") -> Reference:
    """A PowerCube built-in, as the closed loop builds it."""
    return _builtin(name, SPECS, POSITIONS)


def read_reference(path: Path) -> Reference:
    """A file read for the PowerCube's states."""
    return _read(path, NAMES)


def load_reference(path: Path | None, tau: float, name: str = "default") -> Reference:
    """What the closed loop loads for the PowerCube."""
    return _load(path, tau, name, NAMES, SPECS, POSITIONS)


PAPER_REFERENCE = Path(__file__).resolve().parents[1].parent / "shared" / "powercube" / "reference"
POSITION_LIMIT = 2.5  # rad
VELOCITY_LIMIT = 0.8  # rad/s
# Central differences err by dt^2/6 * jerk; the fastest built-in ("reversals") reaches ~1.4e-3 rad/s at dt = 0.01 s.
GRADIENT_TOL = 2e-3


def _small_reference(n: int = 11) -> Reference:
    """A short, irregular-looking but valid trajectory for file round trips."""
    t = np.linspace(0.0, 1.0, n)
    x = np.stack([np.sin(t), np.cos(t), np.cos(t), -np.sin(t)], axis=1)
    return Reference(t=t, x=x, name="test")


def _sign_changes(v: np.ndarray, eps: float = 1e-3) -> int:
    """Reversals of a velocity, ignoring the zero-velocity rests in between."""
    s = np.sign(v[np.abs(v) > eps])
    return int(np.count_nonzero(s[1:] != s[:-1]))


def _reversal_rate(ref: Reference, column: int) -> float:
    """Velocity sign changes per second."""
    return _sign_changes(ref.x[:, column]) / (ref.t[-1] - ref.t[0])


def _write_csv(path: Path, columns: dict[str, np.ndarray]) -> Path:
    np.savetxt(path, np.stack(list(columns.values()), axis=1), delimiter=",", header=",".join(columns), comments="")
    return path


# ---------------------------------------------------------------------------------------------------------------
# Built-ins


@pytest.mark.parametrize("name", sorted(BUILTINS))
def test_builtin_is_feasible_and_consistent(name: str) -> None:
    ref = builtin_reference(name)
    assert ref.name == f"builtin:{name}"
    assert ref.x.shape == (len(ref), 4)
    assert ref.t.shape == (len(ref),)
    assert ref.x.dtype == ref.t.dtype == np.float64
    assert len(ref) > 100
    np.testing.assert_allclose(np.diff(ref.t), BUILTIN_DT, atol=1e-9)
    assert np.abs(ref.x[:, :2]).max() <= POSITION_LIMIT
    assert np.abs(ref.x[:, 2:]).max() <= VELOCITY_LIMIT
    velocity = np.gradient(ref.x[:, :2], ref.t, axis=0)
    np.testing.assert_allclose(ref.x[:, 2:], velocity, atol=GRADIENT_TOL)


def test_default_is_long_starts_at_rest_and_reverses_both_joints() -> None:
    ref = builtin_reference()
    assert ref.name == "builtin:default"
    assert 20.0 <= ref.t[-1] - ref.t[0] <= 30.0
    np.testing.assert_array_equal(ref.x[0, 2:], 0.0)
    assert _sign_changes(ref.x[:, 2]) >= 3
    assert _sign_changes(ref.x[:, 3]) >= 3


def test_reversals_reverse_faster_than_default() -> None:
    fast, default = builtin_reference("reversals"), builtin_reference("default")
    for j in (2, 3):
        assert _reversal_rate(fast, j) > 2 * _reversal_rate(default, j)
    assert np.abs(fast.x[:, 2:]).max() >= 0.65


def test_rest_holds_both_joints_still_for_a_second_or_more() -> None:
    ref = builtin_reference("rest")
    still = np.all(ref.x[:, 2:] == 0.0, axis=1)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], still.astype(int), [0]])))
    lengths = (edges[1::2] - edges[::2] - 1) * BUILTIN_DT
    assert np.count_nonzero(lengths >= 1.0 - 1e-9) >= 4
    assert np.abs(ref.x[:, 2:]).max() > 0.5  # and it does move in between


def test_sine_matches_the_formula() -> None:
    ref = builtin_reference("sine")
    t = ref.t
    np.testing.assert_allclose(ref.x[:, 0], 0.8 * np.sin(2 * np.pi * 0.1 * t), atol=1e-12)
    np.testing.assert_allclose(ref.x[:, 1], 0.6 * np.sin(2 * np.pi * 0.15 * t) + 0.3, atol=1e-12)


def test_sine_lists_of_different_lengths_are_named() -> None:
    specs = {"sine": {"kind": "sine", "amplitude": [0.1, 0.2, 0.3], "frequency": [0.1, 0.2], "offset": [0, 0],
                      "duration": 2.0}}  # fmt: skip
    with pytest.raises(ReferenceError, match=r"'sine': amplitude 3, frequency 2, offset 2 entries; expected one per"):
        _builtin("sine", specs, POSITIONS)


def test_unknown_builtin_lists_valid_names() -> None:
    with pytest.raises(ReferenceError, match=r"unknown built-in reference 'square'.*default, reversals, rest, sine"):
        builtin_reference("square")


@pytest.mark.parametrize("system", ["planar3", "panda"])
def test_builtins_of_other_arms_stay_inside_their_box(system: str) -> None:
    arm = load_system(system)
    specs = OmegaConf.to_container(system_config(system).references)
    positions = (arm.state_box.low[: arm.nq], arm.state_box.high[: arm.nq])
    for name in [*specs, "random-7"]:
        ref = check_states(_builtin(name, specs, positions, arm), arm.state_names)
        assert ref.x.shape[1] == 2 * arm.nq
        assert np.all(ref.x >= np.array(arm.state_box.low)) and np.all(ref.x <= np.array(arm.state_box.high))
        velocity = np.gradient(ref.x[:, : arm.nq], ref.t, axis=0)
        np.testing.assert_allclose(ref.x[:, arm.nq :], velocity, atol=GRADIENT_TOL)


def test_random_references_differ_by_seed_and_start_at_rest_in_the_middle() -> None:
    a, b = builtin_reference("random-1"), builtin_reference("random-2")
    assert a.name == "builtin:random-1" and not np.allclose(a.x, b.x)
    np.testing.assert_allclose(a.x[0], 0.0, atol=1e-12)
    np.testing.assert_array_equal(a.x, builtin_reference("random-1").x)
    with pytest.raises(ReferenceError, match="joint range"):
        _builtin("random", SPECS)


def test_reference_for_another_system_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "three.npz"
    np.savez(path, t=np.arange(3.0), x=np.zeros((3, 6)))
    with pytest.raises(ReferenceError, match="6 columns; this system has 4 states"):
        read_reference(path)
    planar = load_system("planar3")
    columns = {"t": np.arange(3.0), **{n: np.zeros(3) for n in planar.state_names}}
    assert _read(_write_csv(tmp_path / "p3.csv", columns), planar.state_names).x.shape == (3, 6)


# ---------------------------------------------------------------------------------------------------------------
# Files


def test_npz_round_trip_writes_nothing(tmp_path: Path) -> None:
    ref = _small_reference()
    path = tmp_path / "ref.npz"
    np.savez(path, t=ref.t, x=ref.x)
    before = sorted(tmp_path.iterdir())
    back = read_reference(path)
    np.testing.assert_array_equal(back.t, ref.t)
    np.testing.assert_array_equal(back.x, ref.x)
    assert back.name == str(path)
    assert sorted(tmp_path.iterdir()) == before


def test_csv_round_trip(tmp_path: Path) -> None:
    ref = _small_reference()
    columns = {"t": ref.t, **{k: ref.x[:, j] for j, k in enumerate(("alpha", "beta", "dalpha", "dbeta"))}}
    back = read_reference(_write_csv(tmp_path / "ref.csv", columns))
    np.testing.assert_allclose(back.t, ref.t, rtol=1e-15)
    np.testing.assert_allclose(back.x, ref.x, rtol=1e-15)


def test_csv_columns_in_any_order_with_extras(tmp_path: Path) -> None:
    ref = _small_reference()
    columns = {
        "dbeta": ref.x[:, 3],
        "u1": np.zeros(len(ref)),
        "beta": ref.x[:, 1],
        "t": ref.t,
        "dalpha": ref.x[:, 2],
        "alpha": ref.x[:, 0],
    }
    back = read_reference(_write_csv(tmp_path / "ref.csv", columns))
    np.testing.assert_allclose(back.t, ref.t, rtol=1e-15)
    np.testing.assert_allclose(back.x, ref.x, rtol=1e-15)


def test_csv_with_numpy_comment_header(tmp_path: Path) -> None:
    ref = _small_reference()
    path = tmp_path / "ref.csv"
    np.savetxt(path, np.column_stack([ref.t, ref.x]), delimiter=",", header="t,alpha,beta,dalpha,dbeta")
    np.testing.assert_allclose(read_reference(path).x, ref.x, rtol=1e-15)


def test_mat_folder_round_trip(tmp_path: Path) -> None:
    ref = _small_reference()
    scipy.io.savemat(tmp_path / "y_soll.mat", {"y_soll": ref.x[:, :2].T})
    scipy.io.savemat(tmp_path / "Dy_soll.mat", {"Dy_soll": ref.x[:, 2:].T})
    scipy.io.savemat(tmp_path / "t_soll.mat", {"t_soll": ref.t[None, :]})
    back = read_reference(tmp_path)
    np.testing.assert_array_equal(back.t, ref.t)
    np.testing.assert_array_equal(back.x, ref.x)
    assert back.name == str(tmp_path)


def test_paper_reference_folder() -> None:
    if not PAPER_REFERENCE.is_dir():
        pytest.skip(f"paper reference not available at {PAPER_REFERENCE}")
    raw = read_reference(PAPER_REFERENCE)
    assert len(raw) == 1220
    assert raw.t[0] == 0.0
    assert raw.t[-1] == pytest.approx(24.38)
    coarse = resample(raw, 0.2)
    assert len(coarse) == 122
    np.testing.assert_allclose(coarse.t, raw.t[0] + 0.2 * np.arange(122), atol=1e-12)
    np.testing.assert_allclose(coarse.x, raw.x[::10], atol=1e-9)
    np.testing.assert_allclose(load_reference(PAPER_REFERENCE, 0.2).x, coarse.x)


# ---------------------------------------------------------------------------------------------------------------
# Resampling, loading, box check


def test_resample_is_linear_interpolation_on_a_tau_grid() -> None:
    ref = builtin_reference("sine")
    coarse = resample(ref, 0.2)
    np.testing.assert_allclose(np.diff(coarse.t), 0.2, atol=1e-12)
    assert coarse.t[0] == ref.t[0]
    assert coarse.t[-1] <= ref.t[-1] + 1e-9
    assert len(coarse) == 101  # 0.0, 0.2, ..., 20.0
    expected = np.stack([np.interp(coarse.t, ref.t, ref.x[:, j]) for j in range(4)], axis=1)
    np.testing.assert_allclose(coarse.x, expected, atol=1e-12)
    assert coarse.name == ref.name


def test_resample_between_samples_and_from_a_nonzero_start() -> None:
    x = np.array([[0.0, 0.0, 1.0, 1.0], [1.0, 1.0, 1.0, 1.0], [3.0, 3.0, 1.0, 1.0]])  # a ramp at unit speed
    ref = Reference(t=np.array([1.0, 2.0, 4.0]), x=x, name="test")
    coarse = resample(ref, 0.5)
    np.testing.assert_allclose(coarse.t, [1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0])
    np.testing.assert_allclose(coarse.x[:, 0], [0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0])


@pytest.mark.parametrize("tau", [0.0, -0.2, float("nan")])
def test_resample_rejects_nonpositive_tau(tau: float) -> None:
    with pytest.raises(ReferenceError, match="expected a positive"):
        resample(builtin_reference(), tau)


def test_resample_rejects_tau_longer_than_reference() -> None:
    with pytest.raises(ReferenceError, match="longer than the reference"):
        resample(builtin_reference(), 100.0)


def test_load_reference_builtin_and_file(tmp_path: Path) -> None:
    ref = load_reference(None, 0.2, name="rest")
    assert ref.name == "builtin:rest"
    np.testing.assert_allclose(np.diff(ref.t), 0.2, atol=1e-12)
    path = tmp_path / "ref.npz"
    np.savez(path, t=ref.t, x=ref.x)
    from_file = load_reference(path, 0.4)
    np.testing.assert_allclose(from_file.x, ref.x[::2], atol=1e-12)


def test_times_in_milliseconds_are_refused(tmp_path: Path) -> None:
    ref = builtin_reference("default")
    assert velocity_scale(ref) == pytest.approx(1.0, abs=0.01)
    path = tmp_path / "ms.npz"
    np.savez(path, t=1e3 * ref.t, x=ref.x)  # the same motion, its times in ms
    with pytest.raises(ReferenceError, match=r"ms.npz: its velocities are 1000x .* in milliseconds .* seconds"):
        load_reference(path, 0.2)
    np.savez(path, t=ref.t, x=np.hstack([ref.x[:, :2], 0.0 * ref.x[:, 2:]]))  # zero velocities: no unit to judge
    assert velocity_scale(read_reference(path)) == 0.0 and len(load_reference(path, 0.2)) > 1


def test_out_of_box() -> None:
    ref = Reference(t=np.array([0.0, 1.0]), x=np.array([[0.0, 0.5, 0.0, 0.0], [1.0, -2.9, 0.3, 0.0]]), name="test")
    assert out_of_box(ref, [-3, -3, -1, -1], [3, 3, 1, 1]) == 0.0
    assert out_of_box(ref, [-1, -1, -1, -1], [1, 1, 1, 1]) == pytest.approx(1.9)  # beta = -2.9 under -1
    assert out_of_box(ref, [-3, -3, -1, -1], [0.5, 3, 0.1, 1]) == pytest.approx(0.5)  # alpha = 1.0 over 0.5
    with pytest.raises(ReferenceError, match="expected 4 bounds"):
        out_of_box(ref, [-1, -1], [1, 1])


# ---------------------------------------------------------------------------------------------------------------
# Bad input


def _bad_npz_x(p: Path) -> Path:
    np.savez(p / "bad.npz", t=np.arange(5.0), x=np.zeros((5, 3)))
    return p / "bad.npz"


def _bad_csv_column(p: Path) -> Path:
    return _write_csv(
        p / "bad.csv", {"t": np.arange(3.0), "alpha": np.zeros(3), "beta": np.zeros(3), "dalpha": np.zeros(3)}
    )


def _bad_nan(p: Path) -> Path:
    x = np.zeros((6, 4))
    x[4, 2] = np.nan
    np.savez(p / "bad.npz", t=np.arange(6.0), x=x)
    return p / "bad.npz"


def _bad_time(p: Path) -> Path:
    columns = {k: np.zeros(5) for k in ("alpha", "beta", "dalpha", "dbeta")}
    return _write_csv(p / "bad.csv", {"t": np.array([0.0, 0.1, 0.2, 0.2, 0.3]), **columns})


def _bad_truncated_npz(p: Path) -> Path:
    np.savez(p / "full.npz", t=np.arange(50.0), x=np.zeros((50, 4)))
    data = (p / "full.npz").read_bytes()
    (p / "bad.npz").write_bytes(data[: len(data) // 2])
    return p / "bad.npz"


def _bad_garbage_npz(p: Path) -> Path:
    (p / "bad.npz").write_bytes(b"PK\x03\x04 this is not a zip archive")
    return p / "bad.npz"


def _bad_empty_folder(p: Path) -> Path:
    (p / "ref").mkdir()
    return p / "ref"


def _bad_mat_variable(p: Path) -> Path:
    _bad_empty_folder(p)
    for var in ("y_soll", "Dy_soll", "t_soll"):
        scipy.io.savemat(p / "ref" / f"{var}.mat", {"wrong" if var == "Dy_soll" else var: np.zeros((2, 4))})
    return p / "ref"


def _bad_one_sample(p: Path) -> Path:
    np.savez(p / "bad.npz", t=np.zeros(1), x=np.zeros((1, 4)))
    return p / "bad.npz"


def _bad_garbage_csv(p: Path) -> Path:
    (p / "bad.csv").write_text("t,alpha,beta,dalpha,dbeta\n0,0,0,0,0\n1,0,0\n")
    return p / "bad.csv"


def _bad_csv_twice(p: Path) -> Path:
    (p / "bad.csv").write_text("t,alpha,beta,dalpha,dbeta,alpha\n0,0,0,0,0,1\n1,0,0,0,0,1\n")
    return p / "bad.csv"


def _bad_csv_text(p: Path) -> Path:
    (p / "bad.csv").write_text("t,alpha,beta,dalpha,dbeta\n0,0,0,0,0\n\n1,0,abc,0,0\n")  # a blank line is skipped
    return p / "bad.csv"


def _bad_csv_empty(p: Path) -> Path:
    (p / "bad.csv").write_text("t,alpha,beta,dalpha,dbeta\n0,0,0,,0\n1,0,0,0,0\n")
    return p / "bad.csv"


def _bad_complex(p: Path) -> Path:
    np.savez(p / "bad.npz", t=np.arange(5.0), x=np.zeros((5, 4)) + 1j)
    return p / "bad.npz"


@pytest.mark.parametrize(
    ("make", "fragment"),
    [
        (lambda p: p / "nowhere.npz", "no such file or folder"),
        (lambda p: (p / "ref.txt").write_text("1 2 3") and p / "ref.txt", "unknown reference kind '.txt'.*.npz.*.csv"),
        (_bad_npz_x, r"x has shape \(5, 3\), an odd number of columns; expected \(5, nx\)"),
        (_bad_csv_column, "missing column.*dbeta"),
        (_bad_nan, "non-finite state 2 = nan at sample 4"),
        (_bad_time, "not strictly increasing at sample 3"),
        (_bad_truncated_npz, "not a .npz archive"),
        (_bad_garbage_npz, "not a .npz archive"),
        (_bad_empty_folder, "missing y_soll.mat"),
        (_bad_mat_variable, "Dy_soll.mat: no variable 'Dy_soll'"),
        (_bad_one_sample, "1 sample.*expected at least 2"),
        (_bad_garbage_csv, r"Line #3 \(got 3 columns"),
        (_bad_csv_twice, "column\\(s\\) alpha named twice in the header"),
        (_bad_csv_text, "row 2, column beta: 'abc' is not a number"),
        (_bad_csv_empty, "row 1, column dalpha: empty cell"),
        (_bad_complex, "x is complex; expected real"),
    ],
    ids=[
        "missing",
        "extension",
        "npz-shape",
        "csv-column",
        "nan",
        "time",
        "truncated-npz",
        "garbage-npz",
        "empty-folder",
        "mat-variable",
        "one-sample",
        "short-csv-row",
        "csv-column-twice",
        "csv-text-cell",
        "csv-empty-cell",
        "complex",
    ],
)
def test_bad_input_raises_reference_error(tmp_path: Path, make, fragment: str) -> None:
    path = make(tmp_path)
    with pytest.raises(ReferenceError, match=fragment) as info:
        read_reference(path)
    message = str(info.value)
    assert "\n" not in message
    assert str(path) in message
    assert isinstance(info.value, USER_ERRORS)  # the CLI ends it in one line with exit 2, not a traceback


def test_driven_reference_is_a_motion_of_the_true_arm_under_in_box_inputs() -> None:
    arm = load_system("planar3")
    specs = OmegaConf.to_container(system_config("planar3").references)
    positions = (arm.state_box.low[:3], arm.state_box.high[:3])
    ref, path = (
        _builtin("driven", specs, positions, arm),
        _builtin("driven", {**specs, "driven": {**specs["driven"], "kind": "random"}}, positions),
    )
    assert ref.t[-1] == pytest.approx(20.0) and ref.name == "builtin:driven"
    lag = np.sqrt(np.mean((ref.x[:, :3] - path.x[:, :3]) ** 2, axis=0))
    assert np.all(lag > 1e-3) and np.all(lag < 0.1)  # measured 0.03-0.04 rad: it lags the path, it is not the path
    # the inputs that produce its accelerations (a = a0 + B u, from the rhs) lie in the input box
    mid = slice(1, -1)
    acc = np.gradient(ref.x[:, 3:], ref.t, axis=0, edge_order=2)[mid]
    x = ref.x[mid]
    a0 = arm.rhs(x, np.zeros((len(x), 3)))[:, 3:]
    b = np.stack([arm.rhs(x, np.tile(e, (len(x), 1)))[:, 3:] - a0 for e in np.eye(3)], axis=-1)
    u = np.linalg.solve(b, (acc - a0)[..., None])[..., 0]
    slack = 0.02 * np.asarray(arm.input_box.high)  # finite-difference accelerations
    assert np.all(u <= np.asarray(arm.input_box.high) + slack) and np.all(u >= np.asarray(arm.input_box.low) - slack)
    assert np.abs(u).max(axis=0).min() > 0.1 * np.asarray(arm.input_box.high).min()  # it is driven, not resting
    np.testing.assert_array_equal(ref.x, _builtin("driven", specs, positions, arm).x)  # reproducible
    assert not np.allclose(ref.x, _builtin("driven-3", specs, positions, arm).x)
    with pytest.raises(ReferenceError, match="needs the system"):
        _builtin("driven", specs, positions)
    bad = {"driven": {**specs["driven"], "bandwidth": -1.0}}
    with pytest.raises(ReferenceError, match=r"'driven': bandwidth=-1.0; expected a finite number > 0"):
        _builtin("driven", bad, positions, arm)


def test_auto_is_the_papers_reference_only_for_the_arm_it_was_made_for() -> None:
    # reference.path=auto once handed the PowerCube's 4-state file to planar3 (`make robustness system=planar3`)
    assert resolve_reference_path("auto", paper=None) is None  # the system's built-in
    paper = system_config("powercube")["paper_reference"]
    found = str(PAPER_REFERENCE.resolve()) if PAPER_REFERENCE.is_dir() else None
    assert resolve_reference_path("auto", paper=paper) == found  # relative to the project root, wherever run from
    assert resolve_reference_path("auto", paper="no/such/folder") is None
    with pytest.raises(ReferenceError, match="system.paper_reference=True; expected a folder path"):
        resolve_reference_path("auto", paper=True)  # the flag of earlier versions: which file it meant is unknown
    assert resolve_reference_path("auto", paper=False) is None  # ... and false still means none
    assert resolve_reference_path("my.csv", paper=None) == "my.csv" and resolve_reference_path(None) is None
    assert system_config("planar3")["paper_reference"] is None and system_config("panda")["paper_reference"] is None


def _sine(t: np.ndarray, velocity_factor: float = 1.0) -> Reference:
    """A smooth two-joint path sampled at t, its velocities scaled by velocity_factor (1: consistent)."""
    q = np.stack([0.8 * np.sin(0.9 * t), 0.5 * np.cos(0.7 * t)], axis=1)
    v = velocity_factor * np.stack([0.72 * np.cos(0.9 * t), -0.35 * np.sin(0.7 * t)], axis=1)
    return Reference(t=t, x=np.concatenate((q, v), axis=1), name="sine")


def test_coarse_samples_keep_the_path_where_their_velocities_belong_to_it() -> None:
    fine = _sine(np.arange(0.0, 12.0 + 1e-9, 0.2))  # on the grid: the path itself
    coarse = resample(_sine(np.arange(0.0, 12.0 + 1e-9, 0.6)), 0.2)  # three periods between samples
    assert np.abs(coarse.x - fine.x).max(axis=0)[:2].max() < 2e-3  # Hermite with the file's slopes
    linear = resample(_sine(np.arange(0.0, 12.0 + 1e-9, 0.6), velocity_factor=0.0), 0.2)  # no usable velocities
    assert np.abs(linear.x - fine.x).max(axis=0)[:2].max() > 5e-3  # chords: the path's curvature is lost
    on_grid = resample(fine, 0.2)
    np.testing.assert_allclose(on_grid.x, fine.x, rtol=0, atol=1e-12)  # on samples: the samples


def test_velocities_that_do_not_belong_to_the_positions_are_named(caplog) -> None:
    warn_velocities(_sine(np.arange(0.0, 6.0, 0.02)))
    assert not caplog.text
    warn_velocities(_sine(np.arange(0.0, 6.0, 0.02), velocity_factor=0.0))  # positions only, velocities 0
    assert "its velocities are 0 x the rate of change of its positions" in caplog.text


def test_a_reference_of_implausibly_many_periods_is_refused_unless_max_steps_cuts_it() -> None:
    long = Reference(t=np.array([0.0, 1e7]), x=np.zeros((2, 4)), name="long")  # t in microseconds?
    with pytest.raises(ReferenceError, match="t spans 1e.07 s, 50000001 periods of tau=0.2 s; expected t in seconds"):
        resample(long, 0.2)
    assert len(resample(long, 0.2, max_samples=12)) == 12  # what a max_steps run needs, built in no time
