"""What a log must be beyond its format before anything is fitted to it, and what a set of logs must be together.

One log: at least one hold period, and no sample farther outside the system's state box than the box's width (the
rule references and closed loops follow: a log in degrees, or garbage samples, lie there; positions of arms whose
joints turn all the way round are not bounded). A set: no file twice, one robot (what the meta says of it), and no
episode in two places (compared by content, so two collects of one seed are caught whatever their names). Each
refusal is one ValueError naming the file, what was found and what was expected. read_log and read_logs run these,
so identify, training on data.logs and the bench's robot section all check alike.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from pinnmpc.robot_data.logs import RobotLog

log = logging.getLogger(__name__)

EPISODE_RTOL = 1e-9  # relative: samples this close are the same sample (a CSV round trip is exact; other libms not)
ROBOT_KEYS = {"robot": "plant.robot", "robot_effects": "robot_effects"}  # the meta's keys naming the robot
PLANT_KEYS = ("kind", "friction_scale", "mass_scale")  # sources.plant's keys that make it another robot


def check_content(log_: RobotLog, where: str, system: Any) -> None:
    """One log: a period to fit (a one-sample log holds none) and every sample near the state box."""
    periods = int(np.count_nonzero(log_.episode[1:] == log_.episode[:-1]))
    if periods == 0:
        raise ValueError(
            f"robot log {where}: {len(log_.t)} sample(s) and no hold period (no episode has two samples); expected "
            "at least one period: a state, the input held over tau, the next state"
        )
    if system is None or getattr(system, "state_box", None) is None:
        return
    from pinnmpc.simulation.loop import divergence_box, far_outside

    box = divergence_box(system)
    names = log_.meta["state_names"]
    parts = [("", log_.t, log_.x)]
    if log_.t_fine is not None:
        parts.append(("fine part: ", log_.t_fine, log_.x_fine))
    for part, t, x in parts:
        beyond = far_outside(x, box)
        if beyond.any():
            i, j = (int(v) for v in np.argwhere(beyond)[0])
            raise ValueError(
                f"robot log {where}: {part}{names[j]} = {x[i, j]:.6g} at t={t[i]:.6g} lies farther outside the "
                f"state box [{box.low[j]:g}, {box.high[j]:g}] than its width (degrees instead of radians? garbage "
                f"samples?); expected samples near the box (a robot that goes there needs a wider "
                f"system.dynamics.state_box)"
            )


def check_fine_promised(log_: RobotLog, path: Path) -> None:
    """A log whose meta says it was sampled `fine` times per period but comes without that part would be fitted at
    the control rate alone, silently coarser."""
    fine = log_.meta.get("fine")
    if log_.t_fine is not None or isinstance(fine, bool) or not isinstance(fine, int) or fine <= 1:
        return
    if path.suffix == ".csv":
        missing = path.with_name(path.stem + "_fine.csv")
        raise ValueError(
            f"robot log {path}: meta fine={fine} but {missing.name} is missing; expected it beside {path.name} (or "
            f"the log's .npz), or meta fine=1 for a control-rate log"
        )
    raise ValueError(
        f"robot log {path}: meta fine={fine} but no fine arrays (t_fine, x_fine, episode_fine); expected them, or "
        "meta fine=1 for a control-rate log"
    )


def cut_short_note(log_: RobotLog, where: str) -> str | None:
    """A log cut short (a stopped or killed collect) is good data, only less of it: the warning that says so, for
    the output's record (None: a whole log)."""
    why = log_.meta.get("cut_short")
    return f"robot log {where} was cut short ({why}); its {log_.robot_time:g} s are used" if why else None


def warn_cut_short(log_: RobotLog, where: str) -> None:
    """Say it when a log read was cut short."""
    note = cut_short_note(log_, where)
    if note:
        log.warning(note)


def check_set(logs: Sequence[RobotLog], paths: Sequence[str | Path]) -> None:
    """Logs to fit together: each file once, one robot, no episode twice (each would bias the fit or leak held-out
    episodes into training)."""
    _check_files(paths)
    _check_robot(logs, paths)
    _check_episodes(logs, paths)


def _same_file(a: Path, b: Path) -> bool:
    """Whether two paths name one file (links included)."""
    try:
        return os.path.samefile(a, b)
    except OSError:
        return a.resolve() == b.resolve()


def _check_files(paths: Sequence[str | Path]) -> None:
    """No file listed twice."""
    for j, b in enumerate(paths):
        for i, a in enumerate(paths[:j]):
            if _same_file(Path(a), Path(b)):
                raise ValueError(
                    f"robot log {b}: listed twice (logs[{i}] and logs[{j}]); expected each log once (its data would "
                    "count double)"
                )


def robot_of(meta: dict[str, Any]) -> dict[str, Any]:
    """What a log's meta says of the robot it was taken on (only the keys it has), named as the settings that chose
    it."""
    out = {name: meta[key] for key, name in ROBOT_KEYS.items() if key in meta}
    plant = (meta.get("sources") or {}).get("plant")
    if isinstance(plant, dict):
        out.update({f"plant.{k}": plant[k] for k in PLANT_KEYS if k in plant})
    return out


def _check_robot(logs: Sequence[RobotLog], paths: Sequence[str | Path]) -> None:
    """Every log of one robot, where their metas say (a fit to two robots averages them)."""
    first = robot_of(logs[0].meta)
    for path, lg in zip(paths[1:], logs[1:]):
        this = robot_of(lg.meta)
        for key in [k for k in first if k in this and first[k] != this[k]][:1]:
            raise ValueError(
                f"robot log {path}: {key}={this[key]!r}, but {paths[0]} has {key}={first[key]!r}; expected logs "
                "of one robot (identify or fine-tune on each robot's logs apart)"
            )


def _episodes(log_: RobotLog) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """(id, x, u) of each episode at the control rate, u without the last sample's repeat."""
    cut = np.flatnonzero(log_.episode[1:] != log_.episode[:-1]) + 1
    starts, ends = np.r_[0, cut], np.r_[cut, len(log_.t)]
    return [(int(log_.episode[a]), log_.x[a:b], log_.u[a : b - 1]) for a, b in zip(starts, ends)]


def _same_start(xa: np.ndarray, ua: np.ndarray, xb: np.ndarray, ub: np.ndarray) -> bool:
    """Whether two episodes agree on every sample both have (one may be the other cut shorter)."""
    n = min(len(xa), len(xb))
    close = lambda a, b: np.allclose(a, b, rtol=EPISODE_RTOL, atol=EPISODE_RTOL)  # noqa: E731
    return close(xa[:n], xb[:n]) and close(ua[: n - 1], ub[: n - 1])


def _check_episodes(logs: Sequence[RobotLog], paths: Sequence[str | Path]) -> None:
    """No episode twice, within a log or across logs: the same start, the same inputs and the same states as far as
    both go (what a collect of the same seed logs again)."""
    eps = [(k, *e) for k, lg in enumerate(logs) for e in _episodes(lg)]
    if len(eps) < 2:
        return
    first = np.array([np.r_[x[0], u[0] if len(u) else np.full(u.shape[1], np.nan)] for _, _, x, u in eps])
    scale = np.maximum(1.0, np.abs(first))
    for j in range(1, len(eps)):
        near = np.all(np.abs(first[:j] - first[j]) <= EPISODE_RTOL * scale[:j], axis=1)
        for i in np.flatnonzero(near):
            (ka, ea, xa, ua), (kb, eb, xb, ub) = eps[i], eps[j]
            if _same_start(xa, ua, xb, ub):
                raise ValueError(
                    f"robot log {paths[kb]}: episode {eb} repeats episode {ea} of {paths[ka]} (the same samples: a "
                    "copy, or a collect with the same seed); expected logs that share no episode (another seed=)"
                )
