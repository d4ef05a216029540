"""Logs of a robot: what it measured, at the control rate and `fine` times per period, one file format for all.

A log holds episodes of zero-hold control: u[k] is held over [t[k], t[k] + tau) and x[k] is measured at t[k].
The last sample of an episode starts no period; its u repeats the one before (no pair uses it). The fine part
samples the same episodes `fine` times per period and includes the control-rate samples (every fine-th one).
Files: <stem>.npz (arrays, meta as JSON), <stem>.csv (control rate, first line `# meta: {json}`) and
<stem>_fine.csv (the fine part; with the command a robot reported at each fine sample where it reports one, as
columns `<input>_reported`), all written at once or not at all (a collect writes the .npz alone at each episode's
end). Reading runs the checks of checks.py too, and read_logs those of a set.
"""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from pinnmpc.robot_data.checks import check_content, check_fine_promised, check_set, warn_cut_short
from pinnmpc.util.io import atomic_create, atomic_write

META_PREFIX = "# meta: "
REPORTED = "_reported"  # the suffix of the fine CSV's columns of the command a robot reported
TIME_TOL = 1e-6  # relative to the sample period: spacing a log's t may miss it by (float sums of tau)
BOX_TOL = 1e-9  # relative to an input's range: how far u may lie outside the input box
META_KEYS = ("system", "tau", "robot", "seed", "noise_sigma", "state_names", "input_names", "fine", "robot_time_s",
             "created", "command", "sources", "cut_short")  # fmt: skip


@dataclass
class RobotLog:
    """Measured episodes of one robot: control-rate samples plus (optionally) the same episodes sampled finer."""

    t: np.ndarray  # (N,) s, control-rate times
    x: np.ndarray  # (N, nx) measured states at t
    u: np.ndarray  # (N, nu) input held over [t_k, t_k + tau)
    episode: np.ndarray  # (N,) int >= 0; one episode's samples are consecutive, t_k = t_0 + k tau within it
    t_fine: np.ndarray | None = None  # (M,) s; None: no fine part
    x_fine: np.ndarray | None = None  # (M, nx)
    episode_fine: np.ndarray | None = None  # (M,)
    meta: dict[str, Any] = field(default_factory=dict)
    command_fine: np.ndarray | None = None  # (M, nu) the command the robot reported at each fine sample (libfranka's
    #   dq_d: franky's ramp to each period's command and libfranka's filter); None: not reported (simulated robots)

    @property
    def tau(self) -> float:
        """The control period, s."""
        return float(self.meta["tau"])

    @property
    def fine(self) -> int:
        """Samples per period in the fine part (1: none)."""
        return int(self.meta.get("fine") or 1) if self.t_fine is not None else 1

    @property
    def episodes(self) -> np.ndarray:
        """The episode ids in the order they appear."""
        _, first = np.unique(self.episode, return_index=True)
        return self.episode[np.sort(first)]

    @property
    def robot_time(self) -> float:
        """Seconds of held input the log covers (periods that end inside their episode)."""
        return float(np.count_nonzero(period_starts(self.episode)) * self.tau)

    def u_fine(self) -> np.ndarray:
        """(M, nu) the input of each fine sample: that of the period it starts (an episode's last: the one before)."""
        if self.t_fine is None:
            raise ValueError("this log has no fine part")
        period = (np.arange(len(self.t_fine)) - first_index(self.episode_fine)) // self.fine
        ids, first = np.unique(self.episode, return_index=True)  # each episode's first control-rate sample
        return self.u[first[np.searchsorted(ids, self.episode_fine)] + period]


def first_index(episode: np.ndarray) -> np.ndarray:
    """For each sample, the index of its episode's first sample (episodes are consecutive)."""
    change = np.r_[True, episode[1:] != episode[:-1]]
    return np.maximum.accumulate(np.where(change, np.arange(len(episode)), 0))


def period_starts(episode: np.ndarray) -> np.ndarray:
    """Which samples start a period inside their episode (all but each episode's last)."""
    return np.r_[episode[1:] == episode[:-1], False]


# -- writing --------------------------------------------------------------------------------------------------
def _table(log: RobotLog, t: np.ndarray, ep: np.ndarray, x: np.ndarray, u: np.ndarray | None, suffix: str = "") -> str:
    """One CSV: the meta line, a header and rows in full precision (input columns named <input><suffix>)."""
    inputs = [f"{name}{suffix}" for name in log.meta["input_names"]] if u is not None else []
    names = ["t", "episode", *log.meta["state_names"], *inputs]
    out = io.StringIO()
    out.write(META_PREFIX + json.dumps(log.meta, default=str) + "\n")
    out.write(",".join(names) + "\n")
    cols = [t[:, None], x] + ([u] if u is not None else [])
    body = np.concatenate(cols, axis=1)
    for e, row in zip(ep, body):
        out.write(f"{float(row[0])!r},{float(e):.17g}," + ",".join(repr(float(v)) for v in row[1:]) + "\n")
    return out.getvalue()


def log_files(path_stem: str | Path) -> list[Path]:
    """The files a log of this stem is: <stem>.npz, <stem>.csv and <stem>_fine.csv."""
    stem = Path(path_stem)
    stem = stem.with_suffix("") if stem.suffix in (".npz", ".csv") else stem
    return [stem.with_name(stem.name + end) for end in (".npz", ".csv", "_fine.csv")]


def write_log(path_stem: str | Path, log: RobotLog, csv: bool = True, new: bool = False) -> list[Path]:
    """<stem>.csv, (with a fine part) <stem>_fine.csv and <stem>.npz, each atomically; a failure removes the ones
    this call already wrote, so no set is left half-written (the .npz last: an earlier one stays). csv=False: the
    .npz alone; new=True: FileExistsError rather than replace a file."""
    npz, table, fine_table = log_files(path_stem)
    _check(log, str(npz.with_suffix("")), None)
    arrays = {"t": log.t, "x": log.x, "u": log.u, "episode": log.episode}
    if log.t_fine is not None:
        arrays.update(t_fine=log.t_fine, x_fine=log.x_fine, episode_fine=log.episode_fine)
        if log.command_fine is not None:
            arrays["command_fine"] = log.command_fine
    arrays["meta"] = np.array(json.dumps(log.meta, default=str))
    put = atomic_create if new else atomic_write
    jobs: list[tuple[Path, Any]] = []
    if csv:
        jobs.append((table, _text(_table(log, log.t, log.episode, log.x, log.u), put)))
        if log.t_fine is not None:
            fine = _table(log, log.t_fine, log.episode_fine, log.x_fine, log.command_fine, REPORTED)
            jobs.append((fine_table, _text(fine, put)))
    jobs.append((npz, lambda p: put(p, lambda tmp: _savez(tmp, arrays))))
    done: list[Path] = []
    try:
        for path, write in jobs:
            write(path)
            done.append(path)
    except BaseException:
        for path in done:
            path.unlink(missing_ok=True)
        raise
    return [npz, *done[:-1]]


def _savez(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Compressed npz into an open file (np.savez would append .npz to a temporary name)."""
    with open(path, "wb") as f:
        np.savez_compressed(f, **arrays)


def _text(text: str, put: Callable[[Path, Callable[[Path], None]], Path]) -> Any:
    """A writer of text to a path through put (atomic_write or atomic_create): never a half-written file."""
    return lambda path: put(path, lambda p: p.write_text(text, encoding="utf-8"))


# -- reading --------------------------------------------------------------------------------------------------
def read_log(path: str | Path, system: Any) -> RobotLog:
    """A log from .npz or .csv (its `_fine.csv` beside it, if there), checked against the system: each problem is one
    ValueError naming the file, what it found and what was expected."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"robot log {path}: no such file; expected a .npz or .csv written by pinnmpc.collect")
    if path.suffix == ".npz":
        log = _read_npz(path)
    elif path.suffix == ".csv":
        log = _read_csv(path)
    else:
        raise ValueError(f"robot log {path}: suffix {path.suffix!r}; expected .npz or .csv")
    _check(log, str(path), system)
    check_fine_promised(log, path)
    check_content(log, str(path), system)
    warn_cut_short(log, str(path))
    return log


def read_logs(paths: Sequence[str | Path], system: Any) -> list[RobotLog]:
    """Several logs, each checked, and checked as a set (check_set); an empty list is refused."""
    if not paths:
        raise ValueError("robot logs: none given; expected at least one .npz or .csv")
    logs = [read_log(p, system) for p in paths]
    check_set(logs, paths)
    return logs


def _read_npz(path: Path) -> RobotLog:
    """The arrays and the meta of an .npz log."""
    try:
        with np.load(path, allow_pickle=False) as f:
            data = {k: f[k] for k in f.files}
    except Exception as e:
        raise ValueError(
            f"robot log {path}: not a readable .npz ({type(e).__name__}); expected a pinnmpc log"
        ) from None
    missing = [k for k in ("t", "x", "u", "episode") if k not in data]
    if missing:
        raise ValueError(f"robot log {path}: no arrays {missing}; expected t, x, u, episode (and meta)")
    meta = _meta(str(data["meta"]) if "meta" in data else "{}", path)
    fine = {k: data.get(k) for k in ("t_fine", "x_fine", "episode_fine", "command_fine")}
    return RobotLog(data["t"], data["x"], data["u"], data["episode"], meta=meta, **fine)


def _meta(text: str, path: Path) -> dict[str, Any]:
    """The meta JSON object of a log."""
    try:
        meta = json.loads(text)
    except json.JSONDecodeError:
        raise ValueError(f"robot log {path}: meta is not valid JSON; expected a JSON object") from None
    if not isinstance(meta, dict):
        raise ValueError(f"robot log {path}: meta is {type(meta).__name__}; expected a JSON object")
    return meta


def _read_table(path: Path) -> tuple[dict[str, Any], list[str], np.ndarray]:
    """Meta (empty without its line), column names and the numbers of one CSV."""
    lines = path.read_text(encoding="utf-8").splitlines()
    meta: dict[str, Any] = {}
    if lines and lines[0].startswith(META_PREFIX):
        meta = _meta(lines.pop(0)[len(META_PREFIX) :], path)
    if not lines:
        raise ValueError(f"robot log {path}: no header line; expected t, episode, state and input names")
    header = [h.strip() for h in next(csv.reader([lines[0]]))]
    rows = [r for r in csv.reader(lines[1:]) if r]
    bad = [i for i, r in enumerate(rows) if len(r) != len(header)]
    if bad:
        i = bad[0]
        raise ValueError(f"robot log {path}: row {i + 1} has {len(rows[i])} cells; expected {len(header)} (the header)")
    try:
        data = np.array(rows, dtype=np.float64).reshape(len(rows), len(header))
    except ValueError:
        raise ValueError(f"robot log {path}: a cell is not a number; expected numbers in every column") from None
    return meta, header, data


def _read_csv(path: Path) -> RobotLog:
    """A control-rate CSV and, beside it, its fine part; names come from the header (checked later)."""
    meta, header, data = _read_table(path)
    if header[:2] != ["t", "episode"]:
        raise ValueError(f"robot log {path}: columns start {header[:2]}; expected t, episode, states, inputs")
    names = header[2:]
    nx = len(meta["state_names"]) if isinstance(meta.get("state_names"), list) else len(names) * 2 // 3
    meta.setdefault("state_names", names[:nx])
    meta.setdefault("input_names", names[nx:])
    if names != [*meta["state_names"], *meta["input_names"]]:
        raise ValueError(
            f"robot log {path}: columns {names}; expected the meta's state and input names "
            f"{[*meta['state_names'], *meta['input_names']]}"
        )
    log = RobotLog(data[:, 0], data[:, 2 : 2 + nx], data[:, 2 + nx :], _episode_column(data[:, 1], path), meta=meta)
    fine = path.with_name(path.stem + "_fine.csv")
    if fine.is_file():
        fmeta, fheader, fdata = _read_table(fine)
        reported = [f"{name}{REPORTED}" for name in meta["input_names"]]
        if fheader not in (["t", "episode", *meta["state_names"]], ["t", "episode", *meta["state_names"], *reported]):
            raise ValueError(
                f"robot log {fine}: columns {fheader}; expected t, episode, {meta['state_names']} (then {reported})"
            )
        if fmeta and {k: fmeta.get(k) for k in ("system", "tau", "fine")} != {
            k: meta.get(k) for k in ("system", "tau", "fine")
        }:
            raise ValueError(f"robot log {fine}: meta differs from {path.name}'s; expected the same log's fine part")
        meta.setdefault("fine", fmeta.get("fine"))
        nxf, command = 2 + len(meta["state_names"]), None
        if fdata.shape[1] > nxf:
            command = fdata[:, nxf:]
        log = replace(log, t_fine=fdata[:, 0], x_fine=fdata[:, 2:nxf], episode_fine=_episode_column(fdata[:, 1], fine),
                      command_fine=command)  # fmt: skip
    return log


def _episode_column(value: np.ndarray, path: Path) -> np.ndarray:
    """Episode ids as integers (a fractional or non-finite one is refused in _check, which sees the floats)."""
    return value if not np.all(np.isfinite(value)) or np.any(value != np.round(value)) else value.astype(np.int64)


# -- the checks -----------------------------------------------------------------------------------------------
def _check(log: RobotLog, where: str, system: Any) -> None:
    """Everything a reader relies on; the first problem raises a one-line ValueError naming `where`."""

    def fail(what: str) -> None:
        raise ValueError(f"robot log {where}: {what}")

    meta = log.meta
    if system is not None:
        if meta.get("system") is not None and meta["system"] != system.name:
            fail(f"system {meta['system']!r}; expected {system.name!r}")
        for key in ("state_names", "input_names"):
            if meta.get(key) is not None and list(meta[key]) != list(getattr(system, key)):
                fail(f"{key} {list(meta[key])}; expected {list(getattr(system, key))} (system {system.name})")
        if meta.get("tau") is not None and abs(float(meta["tau"]) - system.tau) > 1e-12 * system.tau:
            fail(f"control period tau={meta['tau']}; expected the system's tau={system.tau}")
        meta.setdefault("system", system.name)
        meta.setdefault("tau", system.tau)
        meta.setdefault("state_names", list(system.state_names))
        meta.setdefault("input_names", list(system.input_names))
    for key in ("tau", "state_names", "input_names"):
        if meta.get(key) is None:
            fail(f"meta has no {key}; expected {key} in the meta")
    tau, nx, nu = float(meta["tau"]), len(meta["state_names"]), len(meta["input_names"])
    t, x, u, ep = (np.asarray(a) for a in (log.t, log.x, log.u, log.episode))
    shapes = {"t": t.shape, "x": x.shape, "u": u.shape, "episode": ep.shape}
    n = len(t)
    if t.shape != (n,) or x.shape != (n, nx) or u.shape != (n, nu) or ep.shape != (n,):
        fail(f"array shapes {shapes}; expected t ({n},), x ({n}, {nx}), u ({n}, {nu}), episode ({n},)")
    if n == 0:
        fail("no samples; expected at least one episode")
    _check_series(t, x, ep, tau, "", fail)
    finite = np.isfinite(u).all(axis=1)
    if not finite.all():
        fail(f"non-finite input in row {int(np.argmin(finite))}; expected finite numbers")
    if system is not None:
        low, high = np.asarray(system.input_box.low), np.asarray(system.input_box.high)
        tol = BOX_TOL * (high - low)
        out = (u < low - tol) | (u > high + tol)
        if out.any():
            i, j = (int(v) for v in np.argwhere(out)[0])
            fail(
                f"input {meta['input_names'][j]} = {u[i, j]:.6g} at t={t[i]:.6g} is outside the input box "
                f"[{low[j]:g}, {high[j]:g}]; expected inputs inside it"
            )
    if log.t_fine is not None:
        _check_fine(log, meta, tau, nx, fail)
    log.t, log.x, log.u = t.astype(np.float64), x.astype(np.float64), u.astype(np.float64)
    log.episode = ep.astype(np.int64)


def _check_series(t: np.ndarray, x: np.ndarray, ep: np.ndarray, h: float, part: str, fail: Any) -> None:
    """Finite rows, integer episodes in consecutive blocks, time forwards and spaced h within each episode."""
    finite = np.isfinite(t) & np.isfinite(x).all(axis=1) & np.isfinite(ep)
    if not finite.all():
        fail(f"non-finite value in {part}row {int(np.argmin(finite))}; expected finite numbers")
    bad = (ep < 0) | (ep != np.round(ep))
    if bad.any():
        i = int(np.argmax(bad))
        fail(f"{part}episode {ep[i]!r} in row {i}; expected integers >= 0")
    if len(np.unique(ep)) != 1 + np.count_nonzero(ep[1:] != ep[:-1]):
        fail(f"{part}episode ids {np.unique(ep).tolist()} are interleaved; expected each episode's rows consecutive")
    dt = np.diff(t)
    back = dt <= 0
    if back.any():
        i = int(np.argmax(back))
        fail(f"{part}time goes backwards from t={t[i]:.9g} to {t[i + 1]:.9g} (row {i + 1}); expected increasing t")
    inside = ep[1:] == ep[:-1]
    if not inside.any():
        return
    d = dt[inside]
    if np.all(np.abs(d - d[0]) <= TIME_TOL * h) and abs(d[0] - h) > TIME_TOL * h:
        fail(f"{part}samples {d[0]:.9g} s apart; expected the control period's {h:.9g} s")
    off = np.abs(dt - h) > TIME_TOL * h
    off &= inside
    if off.any():
        i = int(np.argmax(off))
        fail(
            f"{part}gap of {dt[i]:.9g} s in episode {int(ep[i])} at t={t[i]:.9g} (row {i + 1}); expected samples "
            f"{h:.9g} s apart within an episode"
        )


def _check_fine(log: RobotLog, meta: dict[str, Any], tau: float, nx: int, fail: Any) -> None:
    """The fine part: fine samples per period of the same episodes, the control-rate ones among them."""
    tf, xf, ef = (np.asarray(a) for a in (log.t_fine, log.x_fine, log.episode_fine))
    m = len(tf) if tf.ndim == 1 else -1
    if m < 0 or xf.shape != (m, nx) or np.shape(ef) != (m,):
        fail(f"fine array shapes {tf.shape}, {xf.shape}, {np.shape(ef)}; expected ({m},), ({m}, {nx}), ({m},)")
    fine = meta.get("fine")
    if isinstance(fine, bool) or not isinstance(fine, int) or fine < 1:
        fail(f"meta fine={fine!r} with a fine part; expected an integer >= 1 (samples per period)")
    _check_series(tf, xf, ef, tau / fine, "fine part: ", fail)
    ids, counts = np.unique(log.episode, return_counts=True)
    fids, fcounts = np.unique(ef, return_counts=True)
    expect = (counts - 1) * fine + 1
    if not np.array_equal(ids, fids) or not np.array_equal(fcounts, expect):
        fail(f"fine part holds {dict(zip(fids.tolist(), fcounts.tolist()))} samples per episode; expected "
             f"{dict(zip(ids.tolist(), expect.tolist()))} ({fine} per period)")  # fmt: skip
    at = first_index(ef)
    on = (np.arange(m) - at) % fine == 0
    tt, xt = tf[on], xf[on]
    scale = np.maximum(1.0, np.abs(log.x))
    if not (np.allclose(tt, log.t, rtol=0, atol=TIME_TOL * tau) and np.all(np.abs(xt - log.x) <= 1e-9 * scale)):
        fail("fine samples at the control times differ from the control-rate samples; expected them included")
    log.t_fine, log.x_fine, log.episode_fine = tf.astype(np.float64), xf.astype(np.float64), ef.astype(np.int64)
    if log.command_fine is not None:
        cf, nu = np.asarray(log.command_fine), len(meta["input_names"])
        if cf.shape != (m, nu) or not np.isfinite(cf).all():
            finite = bool(np.isfinite(cf).all())
            fail(f"reported commands of shape {cf.shape} (finite: {finite}); expected ({m}, {nu}), finite")
        log.command_fine = cf.astype(np.float64)
