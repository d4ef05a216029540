"""Reference trajectories for closed-loop tracking: the paper's MATLAB files, user files, or built-in paths."""

from __future__ import annotations

import csv
import functools
import math
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.io

STATE_NAMES = ("alpha", "beta", "dalpha", "dbeta")  # column order of Reference.x
CSV_COLUMNS = ("t", *STATE_NAMES)  # columns a .csv reference must name in its header
MAT_FILES = {"y_soll": 2, "Dy_soll": 2, "t_soll": 1}  # paper's .mat files (variable = file stem) and their rows
KINDS = "a folder with y_soll.mat, Dy_soll.mat and t_soll.mat, a .npz (t, x) or a .csv (t, alpha, beta, dalpha, dbeta)"
BUILTIN_DT = 0.01  # s, sampling of the built-in references; fine enough to resample to any controller step
PAPER_REFERENCE = Path(__file__).resolve().parents[2] / "shared" / "powercube" / "reference"  # never copied here
RESAMPLE_SLACK = 1e-9  # s, a grid point this close past the last sample still counts as inside


class ReferenceError(ValueError):
    """Bad reference input; the message names the bad value and what was expected."""


@dataclass(frozen=True, eq=False)
class Reference:
    """A sampled state trajectory the controller tracks; validated on construction so no consumer re-checks it."""

    t: np.ndarray
    x: np.ndarray
    name: str

    def __post_init__(self) -> None:
        """Coerce to float64 copies and reject anything a tracking loop would choke on later."""
        t = _as_float(self.t, "t", self.name)
        x = _as_float(self.x, "x", self.name)
        if t.ndim != 1:
            raise ReferenceError(f"{self.name}: t has shape {t.shape}; expected (N,)")
        if x.shape != (len(t), len(STATE_NAMES)):
            hint = " (transposed?)" if x.shape == (len(STATE_NAMES), len(t)) else ""
            raise ReferenceError(f"{self.name}: x has shape {x.shape}{hint}; expected (N, 4) = ({len(t)}, 4)")
        if len(t) < 2:
            raise ReferenceError(f"{self.name}: {len(t)} sample(s); expected at least 2")
        bad_t = np.flatnonzero(~np.isfinite(t))
        if bad_t.size:
            i = int(bad_t[0])
            raise ReferenceError(f"{self.name}: non-finite time {t[i]} at sample {i}; expected finite numbers")
        bad_x = np.argwhere(~np.isfinite(x))
        if bad_x.size:
            i, j = (int(v) for v in bad_x[0])
            raise ReferenceError(
                f"{self.name}: non-finite {STATE_NAMES[j]} = {x[i, j]} at sample {i} (t={t[i]:g}); "
                "expected finite numbers"
            )
        bad_dt = np.flatnonzero(np.diff(t) <= 0)
        if bad_dt.size:
            i = int(bad_dt[0]) + 1
            raise ReferenceError(
                f"{self.name}: time not strictly increasing at sample {i}: t[{i - 1}]={t[i - 1]:g}, t[{i}]={t[i]:g}; "
                "expected strictly increasing times"
            )
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "x", x)
        object.__setattr__(self, "name", str(self.name))

    def __len__(self) -> int:
        """Number of samples, so callers can size horizons without reaching into the arrays."""
        return len(self.t)


def _as_float(value: object, what: str, name: str) -> np.ndarray:
    """Copy to float64 so a caller's buffer is never aliased and non-numeric input fails with a clear message."""
    try:
        return np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ReferenceError(f"{name}: {what} is not numeric ({exc}); expected float arrays") from None


# ---------------------------------------------------------------------------------------------------------------
# Built-in references: each joint is a chain of quintic (minimum-jerk) blends between waypoints, so position,
# velocity and acceleration are continuous, the velocity is the exact derivative, and every waypoint is reached at rest.
# All stay inside |alpha|, |beta| <= 2.5 rad and |velocity| <= 0.8 rad/s (a blend over q0 -> q1 in d seconds peaks
# at 1.875 |q1 - q0| / d).


@dataclass(frozen=True)
class Waypoints:
    """One joint's path: positions q reached at rest, and the duration of each blend between consecutive ones."""

    q: tuple[float, ...]
    durations: tuple[float, ...]


# "default": ~24 s obstacle-avoidance style path (not the paper's): large swings with reversals in both joints,
# starting and ending at rest; peaks 0.66 rad/s (alpha) and 0.75 rad/s (beta).
DEFAULT_DURATIONS = (3.5, 3.5, 4.0, 3.0, 3.0, 3.5, 3.5)
DEFAULT_ALPHA = Waypoints(q=(-0.8, 0.3, -0.9, 0.5, -0.2, 0.6, -0.5, 0.2), durations=DEFAULT_DURATIONS)
DEFAULT_BETA = Waypoints(q=(1.0, -0.3, 1.1, -0.5, 0.4, -0.4, 1.0, 0.3), durations=DEFAULT_DURATIONS)

# "reversals": 12 s of fast back-and-forth around a centre, both joints peaking at ~0.7 rad/s; beta swings at a
# different rate (1.0 s per swing vs 1.5 s) so the reversals of the two joints do not coincide.
REVERSALS_ALPHA = Waypoints(q=(-0.2, *(0.08, -0.48) * 4, -0.2), durations=(0.75, *(1.5,) * 7, 0.75))
REVERSALS_BETA = Waypoints(q=(0.5, *(0.68, 0.32) * 6, 0.5), durations=(0.5, *(1.0,) * 11, 0.5))

# "rest": 18.5 s of moves separated by rest phases of 1-2 s where both joints hold still (a repeated waypoint), the
# regime where joint B's static friction makes it stick; peaks 0.75 rad/s.
REST_DURATIONS = (1.0, 3.0, 1.5, 3.0, 2.0, 3.0, 1.5, 2.5, 1.0)
REST_ALPHA = Waypoints(q=(0.0, 0.0, 0.9, 0.9, -0.3, -0.3, 0.5, 0.5, -0.4, -0.4), durations=REST_DURATIONS)
REST_BETA = Waypoints(q=(0.5, 0.5, -0.5, -0.5, 0.7, 0.7, 0.0, 0.0, 0.9, 0.9), durations=REST_DURATIONS)

# "sine": (amplitude rad, frequency Hz, offset rad) per joint over 20 s (two alpha periods, three beta periods);
# frequencies in ratio 2:3, so the joints sweep through many relative phases and the pattern closes after 20 s.
SINE_ALPHA = (0.8, 0.1, 0.0)
SINE_BETA = (0.6, 0.15, 0.3)
SINE_DURATION = 20.0


def quintic_blend(t: np.ndarray, waypoints: Waypoints) -> tuple[np.ndarray, np.ndarray]:
    """Position and exact velocity of minimum-jerk blends, held at the ends, so references are dynamically smooth."""
    q = np.asarray(waypoints.q, dtype=np.float64)
    d = np.asarray(waypoints.durations, dtype=np.float64)
    if len(d) != len(q) - 1 or np.any(d <= 0):
        raise ReferenceError(f"waypoints {waypoints}: expected len(q) - 1 positive durations")
    knots = np.concatenate([[0.0], np.cumsum(d)])
    seg = np.clip(np.searchsorted(knots, t, side="right") - 1, 0, len(d) - 1)
    s = np.clip((t - knots[seg]) / d[seg], 0.0, 1.0)
    dq = q[seg + 1] - q[seg]
    pos = q[seg] + dq * s**3 * (10.0 - 15.0 * s + 6.0 * s**2)
    vel = dq / d[seg] * 30.0 * s**2 * (1.0 - s) ** 2
    return pos, vel


def _grid(duration: float) -> np.ndarray:
    """Built-in sample times that hit the end time exactly rather than stopping a float step short."""
    return np.arange(round(duration / BUILTIN_DT) + 1) * BUILTIN_DT


def _waypoint_reference(name: str, alpha: Waypoints, beta: Waypoints) -> Reference:
    """Both joints from their waypoint tables; the shorter one holds its last position until the longer ends."""
    t = _grid(max(sum(alpha.durations), sum(beta.durations)))
    (a, da), (b, db) = quintic_blend(t, alpha), quintic_blend(t, beta)
    return Reference(t=t, x=np.stack([a, b, da, db], axis=1), name=f"builtin:{name}")


def _sine_reference() -> Reference:
    """Sinusoids with analytic velocities: a reference that never rests, unlike the waypoint ones."""
    t = _grid(SINE_DURATION)
    (amp_a, f_a, off_a), (amp_b, f_b, off_b) = SINE_ALPHA, SINE_BETA
    w_a, w_b = 2.0 * math.pi * f_a, 2.0 * math.pi * f_b
    x = np.stack(
        [
            amp_a * np.sin(w_a * t) + off_a,
            amp_b * np.sin(w_b * t) + off_b,
            amp_a * w_a * np.cos(w_a * t),
            amp_b * w_b * np.cos(w_b * t),
        ],
        axis=1,
    )
    return Reference(t=t, x=x, name="builtin:sine")


BUILTINS: dict[str, Callable[[], Reference]] = {
    "default": functools.partial(_waypoint_reference, "default", DEFAULT_ALPHA, DEFAULT_BETA),
    "reversals": functools.partial(_waypoint_reference, "reversals", REVERSALS_ALPHA, REVERSALS_BETA),
    "rest": functools.partial(_waypoint_reference, "rest", REST_ALPHA, REST_BETA),
    "sine": _sine_reference,
}


def builtin_reference(name: str = "default") -> Reference:
    """A project-owned reference, so closed-loop runs work without the paper's data."""
    if name not in BUILTINS:
        raise ReferenceError(f"unknown built-in reference {name!r}; expected one of: {', '.join(BUILTINS)}")
    return BUILTINS[name]()


# ---------------------------------------------------------------------------------------------------------------
# Files


def read_reference(path: str | Path) -> Reference:
    """Load a reference as stored, dispatching on its kind, so resampling stays a separate explicit step."""
    if str(path) == "":
        raise ReferenceError(f"empty reference path; expected {KINDS}, or null for a built-in")
    path = Path(path).expanduser()
    if not path.exists():
        raise ReferenceError(f"{path}: no such file or folder; expected {KINDS}")
    if path.is_dir():
        return _read_mat_folder(path)
    suffix = path.suffix.lower()
    if suffix == ".npz":
        return _read_npz(path)
    if suffix == ".csv":
        return _read_csv(path)
    if suffix == ".mat":
        raise ReferenceError(
            f"{path}: a single .mat file; expected the folder holding y_soll.mat, Dy_soll.mat, t_soll.mat"
        )
    raise ReferenceError(f"{path}: unknown reference kind {suffix or '(no extension)'!r}; expected {KINDS}")


def _read_mat_folder(folder: Path) -> Reference:
    """The paper's layout: one variable per .mat file, each a row-per-signal matrix."""
    arrays: dict[str, np.ndarray] = {}
    for var, rows in MAT_FILES.items():
        file = folder / f"{var}.mat"
        if not file.is_file():
            raise ReferenceError(f"{folder}: missing {file.name}; expected {KINDS}")
        try:
            data = scipy.io.loadmat(file)
        except Exception as exc:  # noqa: BLE001 - scipy raises many types for a bad file; all mean "not readable"
            raise ReferenceError(
                f"{file}: cannot read as MATLAB file ({_one_line(exc)}); expected a -v7 .mat"
            ) from None
        if var not in data:
            found = ", ".join(k for k in data if not k.startswith("__")) or "none"
            raise ReferenceError(f"{file}: no variable {var!r} (found: {found}); expected {var} of shape ({rows}, N)")
        arr = np.asarray(data[var])
        if var == "t_soll" and arr.ndim == 2 and arr.shape[1] == 1:
            arr = arr.T  # a column of times is as unambiguous as a row
        if arr.ndim != 2 or arr.shape[0] != rows:
            raise ReferenceError(f"{file}: {var} has shape {arr.shape}; expected ({rows}, N)")
        arrays[var] = arr
    lengths = {var: arr.shape[1] for var, arr in arrays.items()}
    if len(set(lengths.values())) != 1:
        raise ReferenceError(f"{folder}: sample counts differ {lengths}; expected the same N in every file")
    x = np.concatenate([arrays["y_soll"], arrays["Dy_soll"]], axis=0).T
    return Reference(t=arrays["t_soll"][0], x=x, name=str(folder))


def _read_npz(path: Path) -> Reference:
    """Arrays t (N,) and x (N, 4); no pickles, so a reference file can never run code."""
    try:
        with np.load(path, allow_pickle=False) as data:
            missing = [k for k in ("t", "x") if k not in data.files]
            if missing:
                found = ", ".join(data.files) or "none"
                raise ReferenceError(
                    f"{path}: missing array(s) {', '.join(missing)} (found: {found}); expected t and x"
                )
            t, x = np.asarray(data["t"]), np.asarray(data["x"])
    except ReferenceError:
        raise
    except Exception as exc:  # noqa: BLE001 - zipfile, zlib, numpy format errors all mean "not a readable npz"
        raise ReferenceError(
            f"{path}: cannot read as .npz ({_one_line(exc)}); expected arrays t (N,), x (N, 4)"
        ) from None
    return Reference(t=t, x=x, name=str(path))


def _read_csv(path: Path) -> Reference:
    """Columns found by header name, so column order and extra columns do not matter."""
    try:
        lines = path.read_text(encoding="utf-8-sig").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise ReferenceError(f"{path}: cannot read as text ({_one_line(exc)}); expected a .csv with a header") from None
    start = next((i for i, line in enumerate(lines) if line.strip()), None)
    if start is None:
        raise ReferenceError(f"{path}: empty file; expected a header row naming {', '.join(CSV_COLUMNS)}")
    header = [h.strip().lower() for h in next(csv.reader([lines[start]]))]
    if header:
        header[0] = header[0].lstrip("#").strip()  # np.savetxt writes its header as a "# " comment
    missing = [c for c in CSV_COLUMNS if c not in header]
    if missing:
        raise ReferenceError(
            f"{path}: missing column(s) {', '.join(missing)} (found: {', '.join(header)}); "
            f"expected a header row naming {', '.join(CSV_COLUMNS)}"
        )
    usecols = [header.index(c) for c in CSV_COLUMNS]
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # an empty body warns; it is reported below as too few samples
            data = np.genfromtxt(lines, delimiter=",", skip_header=start + 1, usecols=usecols, dtype=np.float64)
    except ValueError as exc:
        raise ReferenceError(
            f"{path}: cannot parse rows ({_one_line(exc)}); expected numbers in every column"
        ) from None
    data = data.reshape(-1, len(CSV_COLUMNS))
    return Reference(t=data[:, 0], x=data[:, 1:], name=str(path))


def _one_line(exc: Exception) -> str:
    """Exception text squeezed onto one line, so every ReferenceError message stays a single line."""
    text = " ".join(str(exc).split()) or "no details"
    return f"{type(exc).__name__}: {text}"


# ---------------------------------------------------------------------------------------------------------------
# Resampling and checks


def resample(ref: Reference, tau: float) -> Reference:
    """Linear interpolation onto the controller's step tau, so reference samples line up with MPC steps."""
    try:
        tau = float(tau)
    except (TypeError, ValueError):
        tau = math.nan
    if not (math.isfinite(tau) and tau > 0):
        raise ReferenceError(f"{ref.name}: tau={tau!r}; expected a positive, finite sampling time in seconds")
    t0, t_end = ref.t[0], ref.t[-1]
    n = math.floor((t_end - t0 + RESAMPLE_SLACK) / tau) + 1
    if n < 2:
        raise ReferenceError(
            f"{ref.name}: tau={tau:g} s is longer than the reference ({t_end - t0:g} s); expected tau <= the duration"
        )
    t = t0 + tau * np.arange(n)
    i = np.clip(np.searchsorted(ref.t, t, side="right") - 1, 0, len(ref) - 2)
    w = np.clip((t - ref.t[i]) / (ref.t[i + 1] - ref.t[i]), 0.0, 1.0)[:, None]
    x = (1.0 - w) * ref.x[i] + w * ref.x[i + 1]
    return Reference(t=t, x=x, name=ref.name)


def load_reference(path: str | Path | None, tau: float, name: str = "default") -> Reference:
    """What the closed-loop CLI needs: a file if given, else the named built-in, on the controller's grid."""
    ref = builtin_reference(name) if path is None else read_reference(path)
    return resample(ref, tau)


def out_of_box(ref: Reference, low: Sequence[float], high: Sequence[float]) -> float:
    """Largest per-coordinate excursion past the box, to warn when a reference leaves the surrogate's training box."""
    lo, hi = np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64)
    if lo.shape != (len(STATE_NAMES),) or hi.shape != lo.shape:
        raise ReferenceError(f"box low {lo.shape}, high {hi.shape}; expected 4 bounds each ({', '.join(STATE_NAMES)})")
    if np.any(lo > hi):
        raise ReferenceError(f"box low {lo.tolist()} exceeds high {hi.tolist()}; expected low <= high")
    return float(np.max(np.maximum(lo - ref.x, ref.x - hi).clip(min=0.0)))


def resolve_reference_path(path: str | Path | None) -> str | None:
    """'auto': the paper's reference in ../shared when it exists, else None (a built-in); other values as given."""
    if str(path) == "auto":
        return str(PAPER_REFERENCE) if PAPER_REFERENCE.is_dir() else None
    return None if path is None else str(path)
