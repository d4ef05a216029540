"""Reference trajectories for closed-loop tracking: the paper's MATLAB files, user files, or built-in paths."""

from __future__ import annotations

import csv
import math
import warnings
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import scipy.io

MAT_FILES = ("y_soll", "Dy_soll", "t_soll")  # paper's layout: positions (nq, N), velocities (nq, N), times (1, N)
KINDS = "a folder with y_soll.mat, Dy_soll.mat and t_soll.mat, a .npz (t, x) or a .csv (t and the state names)"
BUILTIN_DT = 0.01  # s, sampling of the built-in references; fine enough to resample to any controller step
PROJECT_ROOT = Path(__file__).resolve().parents[1]  # a system's paper_reference is relative to it
RESAMPLE_SLACK = 1e-9  # s, a grid point this close past the last sample still counts as inside
MILLISECONDS = (300.0, 3000.0)  # velocities this many times the positions' rate of change: t was given in ms


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
        if x.ndim != 2 or x.shape[0] != len(t) or x.shape[1] < 2 or x.shape[1] % 2:
            hint = " (transposed?)" if x.ndim == 2 and x.shape[1] == len(t) else ""
            hint = hint or (", an odd number of columns" if x.ndim == 2 and x.shape[1] % 2 else "")
            raise ReferenceError(
                f"{self.name}: x has shape {x.shape}{hint}; expected ({len(t)}, nx): positions, then velocities"
            )
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
                f"{self.name}: non-finite state {j} = {x[i, j]} at sample {i} (t={t[i]:g}); expected finite numbers"
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
    if np.iscomplexobj(value):  # a cast would drop the imaginary parts with only a warning
        raise ReferenceError(f"{name}: {what} is complex; expected real float arrays")
    try:
        return np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ReferenceError(f"{name}: {what} is not numeric ({exc}); expected float arrays") from None


# ---------------------------------------------------------------------------------------------------------------
# Built-in references, described as data in conf/system/<name>.yaml (`references:`), one entry per name:
#   {kind: waypoints, joints: [{q: [...], durations: [...]}, ...]}: each joint a chain of quintic (minimum-jerk)
#       blends between positions reached at rest, so position, velocity and acceleration are continuous;
#   {kind: sine, amplitude: [...], frequency: [...], offset: [...], duration: s}: sinusoids per joint;
#   {kind: random, moves: n, duration: s, fraction: f}: quintic moves between random waypoints in the middle
#       fraction f of the state box (name it `random-<seed>` to pick the seed, default 0);
#   {kind: driven, moves, duration, fraction, bandwidth: rad/s, damping}: the true system driven around such a
#       random path by a loose feedback (pinnmpc/driven.py): a motion the true model makes with in-box inputs.


@dataclass(frozen=True)
class Waypoints:
    """One joint's path: positions q reached at rest, and the duration of each blend between consecutive ones."""

    q: tuple[float, ...]
    durations: tuple[float, ...]


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


def waypoint_reference(name: str, joints: Sequence[Waypoints]) -> Reference:
    """Every joint from its waypoint table; shorter ones hold their last position until the longest ends."""
    t = _grid(max(sum(w.durations) for w in joints))
    pos, vel = zip(*(quintic_blend(t, w) for w in joints))
    return Reference(t=t, x=np.stack([*pos, *vel], axis=1), name=f"builtin:{name}")


def sine_reference(
    name: str, amplitude: Sequence[float], frequency: Sequence[float], offset: Sequence[float], duration: float
) -> Reference:
    """Sinusoids with analytic velocities: a reference that never rests, unlike the waypoint ones."""
    sizes = {key: np.size(v) for key, v in (("amplitude", amplitude), ("frequency", frequency), ("offset", offset))}
    if len(set(sizes.values())) > 1:
        found = ", ".join(f"{key} {n}" for key, n in sizes.items())
        raise ReferenceError(f"built-in reference {name!r}: {found} entries; expected one per joint in each")
    t = _grid(duration)
    a, f, c = (np.asarray(v, dtype=np.float64)[None, :] for v in (amplitude, frequency, offset))
    w = 2.0 * math.pi * f
    x = np.concatenate([a * np.sin(w * t[:, None]) + c, a * w * np.cos(w * t[:, None])], axis=1)
    return Reference(t=t, x=x, name=f"builtin:{name}")


def random_waypoints(
    low: Sequence[float], high: Sequence[float], seed: int, moves: int, duration: float, fraction: float
) -> list[Waypoints]:
    """Per joint: random waypoints in the middle `fraction` of its position range, `duration` s apart."""
    lo, hi = np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64)
    mid, half = (lo + hi) / 2, fraction * (hi - lo) / 2
    q = mid + half * np.random.default_rng(seed).uniform(-1.0, 1.0, size=(int(moves) + 1, len(lo)))
    q[0] = mid  # start at rest in the middle, where every run of this reference begins
    return [Waypoints(tuple(q[:, j]), (float(duration),) * int(moves)) for j in range(len(lo))]


def random_reference(
    name: str, low: Sequence[float], high: Sequence[float], seed: int, moves: int, duration: float, fraction: float
) -> Reference:
    """Quintic moves of every joint between random waypoints in the middle `fraction` of its position range."""
    return waypoint_reference(name, random_waypoints(low, high, seed, moves, duration, fraction))


def driven_reference(
    name: str, system: Any, joints: Sequence[Waypoints], bandwidth: object, damping: object
) -> Reference:
    """The true system driven around the waypoint path by a loose feedback (pinnmpc/driven.py), sampled."""
    from pinnmpc.driven import check_gains, drive

    gains = check_gains(name, bandwidth, damping)
    duration = max(sum(w.durations) for w in joints)
    t = _grid(duration)

    def path(time: float) -> tuple[np.ndarray, np.ndarray]:
        """The path's joint positions and velocities at one time."""
        pos, vel = zip(*(quintic_blend(np.array([time]), w) for w in joints))
        return np.concatenate(pos), np.concatenate(vel)

    return Reference(t=t, x=drive(system, path, duration, t, *gains), name=f"builtin:{name}")


def builtin_reference(
    name: str,
    specs: dict[str, Any],
    position_box: tuple[Sequence[float], Sequence[float]] | None = None,
    system: Any = None,
) -> Reference:
    """A reference described in the system's config (`references:`), so closed loops run without data files;
    a driven one also needs the system it drives."""
    spec, seed = specs.get(name), None
    base, _, suffix = name.rpartition("-")
    if spec is None and suffix.isdigit() and base in specs:
        spec, seed = specs[base], int(suffix)
    if not isinstance(spec, dict):
        raise ReferenceError(f"unknown built-in reference {name!r}; expected one of: {', '.join(specs)}")
    kind = spec.get("kind")
    try:
        if kind == "waypoints":
            joints = [Waypoints(tuple(j["q"]), tuple(j["durations"])) for j in spec["joints"]]
            return waypoint_reference(name, joints)
        if kind == "sine":
            keys = ("amplitude", "frequency", "offset", "duration")
            return sine_reference(name, *(spec[k] for k in keys))
        if kind in ("random", "driven"):
            if position_box is None or (kind == "driven" and system is None):
                raise ReferenceError(f"built-in reference {name!r} needs the system (its joint range)")
            seed = int(spec.get("seed", 0)) if seed is None else seed
            keys = (spec["moves"], spec["duration"], spec.get("fraction", 0.5))
            if kind == "random":
                return random_reference(name, *position_box, seed, *keys)
            joints = random_waypoints(*position_box, seed, *keys)
            return driven_reference(name, system, joints, spec["bandwidth"], spec["damping"])
    except (KeyError, TypeError) as e:
        raise ReferenceError(f"built-in reference {name!r}: malformed spec {spec} ({e!r})") from None
    except ValueError as e:
        raise ReferenceError(str(e)) from None
    raise ReferenceError(f"built-in reference {name!r}: kind={kind!r}; expected waypoints, sine, random or driven")


# ---------------------------------------------------------------------------------------------------------------
# Files


def read_reference(path: str | Path, state_names: Sequence[str]) -> Reference:
    """Load a reference as stored, dispatching on its kind, so resampling stays a separate explicit step."""
    if str(path) == "":
        raise ReferenceError(f"empty reference path; expected {KINDS}, or null for a built-in")
    path = Path(path).expanduser()
    if not path.exists():
        raise ReferenceError(f"{path}: no such file or folder; expected {KINDS}")
    if path.is_dir():
        ref = _read_mat_folder(path)
    elif path.suffix.lower() == ".npz":
        ref = _read_npz(path)
    elif path.suffix.lower() == ".csv":
        ref = _read_csv(path, state_names)
    elif path.suffix.lower() == ".mat":
        raise ReferenceError(
            f"{path}: a single .mat file; expected the folder holding y_soll.mat, Dy_soll.mat, t_soll.mat"
        )
    else:
        raise ReferenceError(f"{path}: unknown reference kind {path.suffix or '(no extension)'!r}; expected {KINDS}")
    return check_states(ref, state_names)


def check_states(ref: Reference, state_names: Sequence[str]) -> Reference:
    """The reference must have one column per state of the system it is tracked on."""
    if ref.x.shape[1] != len(state_names):
        raise ReferenceError(
            f"{ref.name}: x has {ref.x.shape[1]} columns; this system has {len(state_names)} states "
            f"({', '.join(state_names)})"
        )
    return ref


def _read_mat_folder(folder: Path) -> Reference:
    """The paper's layout: one variable per .mat file, each a row-per-signal matrix."""
    arrays: dict[str, np.ndarray] = {}
    for var in MAT_FILES:
        file = folder / f"{var}.mat"
        if not file.is_file():
            raise ReferenceError(f"{folder}: missing {file.name}; expected {KINDS}")
        try:
            data = scipy.io.loadmat(file)
        except Exception as exc:  # scipy raises many types for a bad file; all mean "not readable"
            raise ReferenceError(
                f"{file}: cannot read as MATLAB file ({_one_line(exc)}); expected a -v7 .mat"
            ) from None
        if var not in data:
            found = ", ".join(k for k in data if not k.startswith("__")) or "none"
            raise ReferenceError(f"{file}: no variable {var!r} (found: {found}); expected {var} (rows, N)")
        arr = np.asarray(data[var])
        if var == "t_soll" and arr.ndim == 2 and arr.shape[1] == 1:
            arr = arr.T  # a column of times is as unambiguous as a row
        if arr.ndim != 2 or (var == "t_soll" and arr.shape[0] != 1):
            raise ReferenceError(
                f"{file}: {var} has shape {arr.shape}; expected ({'1' if var == 't_soll' else 'nq'}, N)"
            )
        arrays[var] = arr
    if arrays["y_soll"].shape[0] != arrays["Dy_soll"].shape[0]:
        raise ReferenceError(
            f"{folder}: y_soll has {arrays['y_soll'].shape[0]} rows, Dy_soll {arrays['Dy_soll'].shape[0]}; "
            "expected one row per joint in both"
        )
    lengths = {var: arr.shape[1] for var, arr in arrays.items()}
    if len(set(lengths.values())) != 1:
        raise ReferenceError(f"{folder}: sample counts differ {lengths}; expected the same N in every file")
    x = np.concatenate([arrays["y_soll"], arrays["Dy_soll"]], axis=0).T
    return Reference(t=arrays["t_soll"][0], x=x, name=str(folder))


def _read_npz(path: Path) -> Reference:
    """Arrays t (N,) and x (N, nx); no pickles, so a reference file can never run code."""
    if path.is_file() and not zipfile.is_zipfile(path):  # else numpy blames pickles, whatever the file holds
        raise ReferenceError(f"{path}: not a .npz archive; expected arrays t (N,), x (N, nx) as np.savez writes them")
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
    except Exception as exc:  # zipfile, zlib, numpy format errors all mean "not a readable npz"
        raise ReferenceError(
            f"{path}: cannot read as .npz ({_one_line(exc)}); expected arrays t (N,), x (N, nx)"
        ) from None
    return Reference(t=t, x=x, name=str(path))


def _read_csv(path: Path, state_names: Sequence[str]) -> Reference:
    """Columns found by header name (t and the system's state names), so order and extra columns do not matter."""
    columns = ("t", *(n.lower() for n in state_names))
    try:
        lines = path.read_text(encoding="utf-8-sig").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise ReferenceError(f"{path}: cannot read as text ({_one_line(exc)}); expected a .csv with a header") from None
    start = next((i for i, line in enumerate(lines) if line.strip()), None)
    if start is None:
        raise ReferenceError(f"{path}: empty file; expected a header row naming {', '.join(columns)}")
    header = [h.strip().lower() for h in next(csv.reader([lines[start]]))]
    if header:
        header[0] = header[0].lstrip("#").strip()  # np.savetxt writes its header as a "# " comment
    twice = [c for c in columns if header.count(c) > 1]
    if twice:
        raise ReferenceError(f"{path}: column(s) {', '.join(twice)} named twice in the header; expected each once")
    missing = [c for c in columns if c not in header]
    if missing:
        raise ReferenceError(
            f"{path}: missing column(s) {', '.join(missing)} (found: {', '.join(header)}); "
            f"expected a header row naming {', '.join(columns)}"
        )
    usecols = [header.index(c) for c in columns]
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # an empty body warns; it is reported below as too few samples
            data = np.genfromtxt(lines, delimiter=",", skip_header=start + 1, usecols=usecols, dtype=np.float64)
    except ValueError as exc:
        raise ReferenceError(
            f"{path}: cannot parse rows ({_one_line(exc)}); expected numbers in every column"
        ) from None
    data = data.reshape(-1, len(columns))
    _refuse_text_cells(path, lines[start + 1 :], data, usecols, columns)
    return Reference(t=data[:, 0], x=data[:, 1:], name=str(path))


def _refuse_text_cells(path: Path, body: list[str], data: np.ndarray, usecols: list[int], columns: tuple) -> None:
    """genfromtxt reads a cell that is no number (text, a decimal comma) as NaN: name the cell and its text instead."""
    if np.isfinite(data).all():
        return
    rows = [line for line in body if line.strip() and not line.lstrip().startswith("#")]  # the rows genfromtxt read
    i, j = (int(v) for v in np.argwhere(~np.isfinite(data))[0])
    cells = next(csv.reader([rows[i]])) if i < len(rows) else []
    text = cells[usecols[j]].strip() if usecols[j] < len(cells) else ""
    if text.lower() in ("nan", "inf", "+inf", "-inf", "infinity", "-infinity"):
        return  # a genuine non-finite number: the Reference check reports it
    raise ReferenceError(
        f"{path}: row {i + 1}, column {columns[j]}: {repr(text) + ' is not a number' if text else 'empty cell'}; "
        "expected numbers with a decimal point"
    )


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


def load_reference(
    path: str | Path | None,
    tau: float,
    name: str,
    state_names: Sequence[str],
    builtins: dict[str, Any],
    position_box: tuple[Sequence[float], Sequence[float]] | None = None,
    joint_limits: tuple[Sequence[float], Sequence[float]] | None = None,
    system: Any = None,
) -> Reference:
    """What the closed-loop CLI needs: a file if given, else the named built-in, on the controller's grid.

    builtins is the system's `references:` config; position_box its joint range, for random references;
    joint_limits (low, high) its joint position limits: a reference that leaves them is refused; system the
    true model a driven built-in drives."""
    if path is None:
        ref = check_states(builtin_reference(name, builtins, position_box, system), state_names)
    else:
        ref = read_reference(path, state_names)
        check_time_unit(ref)
    if joint_limits is not None:
        check_joint_limits(ref, *joint_limits, state_names)
    return resample(ref, tau)


def velocity_scale(ref: Reference) -> float | None:
    """How many times the stored velocities exceed the positions' rate of change over t (least squares; None when
    the positions do not move): ~1 for a consistent reference, ~1000 when t is in milliseconds."""
    nq = ref.x.shape[1] // 2
    if len(ref) < 3:
        return None
    rate = np.gradient(ref.x[:, :nq], ref.t, axis=0)
    den = float((rate * rate).sum())
    return None if den == 0.0 else float((ref.x[:, nq:] * rate).sum() / den)


def check_time_unit(ref: Reference) -> None:
    """A file whose velocities are ~1000x its positions' rate of change has its times in ms: refused, since it
    would be run 1000x too slowly (hours for a reference of seconds)."""
    scale = velocity_scale(ref)
    if scale is not None and MILLISECONDS[0] <= scale <= MILLISECONDS[1]:
        raise ReferenceError(
            f"{ref.name}: its velocities are {scale:.0f}x the rate of change of its positions over t: are the times "
            f"in milliseconds (t ends at {ref.t[-1]:g})? expected t in seconds"
        )


def excursions(ref: Reference, low: Sequence[float], high: Sequence[float], columns: int | None = None) -> np.ndarray:
    """How far each sample lies past the box (0 inside), (N, columns): the first `columns` states (None: all)."""
    n = ref.x.shape[1] if columns is None else columns
    lo, hi = np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64)
    if lo.shape != (n,) or hi.shape != lo.shape:
        raise ReferenceError(f"box low {lo.shape}, high {hi.shape}; expected {n} bounds each")
    if np.any(lo > hi):
        raise ReferenceError(f"box low {lo.tolist()} exceeds high {hi.tolist()}; expected low <= high")
    x = ref.x[:, :n]
    return np.maximum(lo - x, x - hi).clip(min=0.0)


def out_of_box(ref: Reference, low: Sequence[float], high: Sequence[float]) -> float:
    """Largest per-coordinate excursion past the box, to warn when a reference leaves the surrogate's training box."""
    return float(np.max(excursions(ref, low, high)))


def check_joint_limits(
    ref: Reference, low: Sequence[float], high: Sequence[float], state_names: Sequence[str] = ()
) -> Reference:
    """Refuse a reference with any position sample outside the joint limits [low, high] (one per joint, positions
    first in the state), naming the joint, the worst sample's time and value, and the limit it passes."""
    beyond = excursions(ref, low, high, len(low))
    if not beyond.any():
        return ref
    i, j = np.unravel_index(int(np.argmax(beyond)), beyond.shape)
    q, lo, hi = ref.x[i, j], float(low[j]), float(high[j])
    side, limit = ("above its upper", hi) if q > hi else ("below its lower", lo)
    joint = state_names[j] if j < len(state_names) else f"joint {j}"
    count = int(np.count_nonzero(beyond.any(axis=1)))
    raise ReferenceError(
        f"{ref.name}: reference leaves the joint limits: {joint} = {q:.6g} at t={ref.t[i]:g} s (sample {i}, worst of "
        f"{count} samples outside) is {beyond[i, j]:.3g} {side} limit {limit:g}; expected every position in "
        f"[{lo:g}, {hi:g}]"
    )


def resolve_reference_path(path: str | Path | None, paper: str | Path | None = None) -> str | None:
    """'auto': the system's paper reference (system.paper_reference, relative to the project root; data never
    copied into the project) when it exists, else None (the system's built-in); other values as given."""
    if paper is False:  # the flag of earlier system configs: false meant none
        paper = None
    if paper is not None and not isinstance(paper, (str, Path)):
        raise ReferenceError(
            f"system.paper_reference={paper!r}; expected a folder path (relative to the project root) or null"
        )
    if str(path) == "auto":
        found = None if paper is None else PROJECT_ROOT / Path(paper)
        return str(found.resolve()) if found is not None and found.is_dir() else None
    return None if path is None else str(path)
