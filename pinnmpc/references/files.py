"""Reference trajectories for closed-loop tracking: the paper's MATLAB files, user files, or built-in paths."""

from __future__ import annotations

import csv
import logging
import math
import warnings
import zipfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import scipy.io
from scipy.interpolate import CubicHermiteSpline

from pinnmpc.references.builtin import BUILTIN_DT as BUILTIN_DT  # re-exported: where references live for users
from pinnmpc.references.builtin import builtin_reference
from pinnmpc.references.data import Reference as Reference
from pinnmpc.references.data import ReferenceError as ReferenceError

MAT_FILES = ("y_soll", "Dy_soll", "t_soll")  # paper's layout: positions (nq, N), velocities (nq, N), times (1, N)
KINDS = "a folder with y_soll.mat, Dy_soll.mat and t_soll.mat, a .npz (t, x) or a .csv (t and the state names)"
PROJECT_ROOT = Path(__file__).resolve().parents[2]  # a system's paper_reference is relative to it
RESAMPLE_SLACK = 1e-9  # s, a grid point this close past the last sample still counts as inside
MILLISECONDS = (300.0, 3000.0)  # velocities this many times the positions' rate of change: t was given in ms
CONSISTENT = (0.5, 2.0)  # ... and this many times: velocities that belong to the positions (else a warning)
MAX_PERIODS = 1_000_000  # a reference longer than this many control periods is refused unless max_steps cuts it
log = logging.getLogger(__name__)

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
            if t.ndim == 2 and 1 in t.shape:  # a column or row vector of times, as MATLAB writes them
                t = t.reshape(-1)
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
    lines = [",".join(row) for row in csv.reader(lines)]  # quoted cells ("0.1") read as their text
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
        other = next(
            (name for d, name in ((";", "semicolons"), ("\t", "tabs")) if len(header) == 1 and d in header[0]), ""
        )
        hint = f" (separated by {other}? expected commas)" if other else ""
        raise ReferenceError(
            f"{path}: missing column(s) {', '.join(missing)} (found: {', '.join(header)}){hint}; "
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


def resample(ref: Reference, tau: float, max_samples: int | None = None) -> Reference:
    """The reference on the controller's step tau, so reference samples line up with MPC steps: the first
    max_samples (None: all). Between samples cubic Hermite in the positions with the file's velocities as their
    slopes (so coarse samples keep the path's curvature) where those velocities belong to the positions, else
    linear; on samples either gives the samples themselves."""
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
    if max_samples is not None:
        n = min(n, max(2, int(max_samples)))
    elif n > MAX_PERIODS:
        raise ReferenceError(
            f"{ref.name}: t spans {t_end - t0:g} s, {n} periods of tau={tau:g} s; expected t in seconds and at most "
            f"{MAX_PERIODS} periods (or set max_steps)"
        )
    t = t0 + tau * np.arange(n)
    scale, nq = velocity_scale(ref), ref.x.shape[1] // 2
    if ref.x.shape[1] % 2 == 0 and scale is not None and CONSISTENT[0] <= scale <= CONSISTENT[1]:
        path = CubicHermiteSpline(ref.t, ref.x[:, :nq], ref.x[:, nq:], extrapolate=False)
        tc = np.clip(t, ref.t[0], ref.t[-1])
        return Reference(t=t, x=np.concatenate((path(tc), path.derivative()(tc)), axis=1), name=ref.name)
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
    max_samples: int | None = None,
) -> Reference:
    """What the closed-loop CLI needs: a file if given, else the named built-in, on the controller's grid.

    builtins is the system's `references:` config; position_box its joint range, for random references;
    joint_limits (low, high) its joint position limits: a reference that leaves them is refused; system the
    true model a driven built-in drives; max_samples how many grid samples a run can use (None: all)."""
    if path is None:
        ref = check_states(builtin_reference(name, builtins, position_box, system), state_names)
    else:
        ref = read_reference(path, state_names)
        check_time_unit(ref)
        warn_velocities(ref)
    if joint_limits is not None:
        check_joint_limits(ref, *joint_limits, state_names)
    return resample(ref, tau, max_samples)


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


def warn_velocities(ref: Reference) -> None:
    """Velocities that do not belong to the positions are tracked as given, which is rarely what was meant: say so
    (columns in another order, velocities in other units, or none given)."""
    scale = velocity_scale(ref)
    if scale is not None and not CONSISTENT[0] <= scale <= CONSISTENT[1]:
        log.warning(
            "reference %s: its velocities are %.3g x the rate of change of its positions (expected ~1): columns in "
            "another order, velocities in other units, or none given? They are tracked as given, and the positions "
            "are interpolated linearly between samples",
            ref.name,
            scale,
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
