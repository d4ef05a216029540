"""Reusable matplotlib figures: built on bare Figure objects so library code never touches pyplot's global state."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np
from matplotlib.animation import FuncAnimation, PillowWriter
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import NullFormatter

from pinnmpc.io import atomic_write

STATE_NAMES = ("alpha", "beta", "dalpha", "dbeta")
STATE_UNITS = ("rad", "rad", "rad/s", "rad/s")
INPUT_NAMES = ("u1", "u2")
INPUT_UNITS = ("A", "A")

# Display defaults only: nothing here is a model parameter.
LINK_LENGTHS = (0.5, 0.4)  # m, drawing lengths of the two links (not the identified PowerCube geometry)
DPI = 120  # PNG resolution: legible on screen, small on disk
FPS = 10  # GIF playback rate
MAX_FRAMES = 300  # GIF frame cap: keeps file size and render time bounded for long runs
ERROR_FLOOR = 1e-12  # absolute floor: exact zeros are clipped up so they stay visible on a log axis
ERROR_DECADES = 6  # ... and to this many decades below the largest error, so one exact zero does not squash the axis
MAX_XTICKS = 12  # scaling plots label each measured x when there are few, else leave log ticks
MAX_MARKERS = 25  # markers per curve: dense markers would hide the line they annotate
TRACKING_FIGSIZE = (10.0, 9.0)
SCALING_FIGSIZE = (6.5, 4.5)
ARM_FIGSIZE = (5.0, 5.0)


class Labels(NamedTuple):
    """Names and units of states and inputs, for systems other than the PowerCube."""

    state_names: Sequence[str] = STATE_NAMES
    state_units: Sequence[str] = STATE_UNITS
    input_names: Sequence[str] = INPUT_NAMES
    input_units: Sequence[str] = INPUT_UNITS


def _as_2d(name: str, a: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """Fail with the array's name: a transposed trajectory otherwise plots as silent nonsense."""
    a = np.asarray(a, dtype=float)
    if a.shape != (rows, cols):
        raise ValueError(f"{name} must have shape ({rows}, {cols}), got {a.shape}")
    return a


def _time(t: np.ndarray) -> np.ndarray:
    """1-D time vector with at least two samples: one sample has no time axis to draw."""
    t = np.asarray(t, dtype=float)
    if t.ndim != 1 or t.size < 2:
        raise ValueError(f"t must be 1-D with at least 2 samples, got shape {t.shape}")
    return t


def _held_inputs(t: np.ndarray, u: np.ndarray, n_inputs: int) -> np.ndarray:
    """Repeat the last input so steps-post draws the final hold interval up to t[-1]."""
    u = np.asarray(u, dtype=float)
    if u.ndim != 2 or u.shape[1] != n_inputs or u.shape[0] not in (t.size - 1, t.size):
        raise ValueError(f"u must have shape ({t.size - 1}, {n_inputs}) (or one row per sample), got {u.shape}")
    return np.vstack([u, u[-1:]]) if u.shape[0] == t.size - 1 else u


def _label(name: str, unit: str) -> str:
    """Axis label with unit, so every panel reads on its own."""
    return f"{name} [{unit}]"


def _plot_inputs(
    ax: Axes,
    t: np.ndarray,
    u_held: np.ndarray,
    names: Sequence[str],
    units: Sequence[str],
    u_low: Sequence[float] | None = None,
    u_high: Sequence[float] | None = None,
) -> None:
    """Zero-hold steps, since that is what the plant actually received between samples."""
    # identical bounds drawn once in black: per-input coloured lines would hide each other
    shared = u_low is not None and u_high is not None and len(set(u_low)) == 1 and len(set(u_high)) == 1
    for i, name in enumerate(names):
        color = f"C{i}"
        ax.plot(t, u_held[:, i], drawstyle="steps-post", color=color, lw=1.4, label=name)
        if u_low is not None and u_high is not None and not shared:
            for j, bound in enumerate((u_low[i], u_high[i])):
                ax.axhline(bound, color=color, ls="--", lw=0.9, alpha=0.8, label=f"{name} bounds" if j == 0 else None)
    if u_low is not None and u_high is not None and shared:
        for j, bound in enumerate((u_low[0], u_high[0])):
            ax.axhline(bound, color="k", ls="--", lw=0.9, alpha=0.7, label="bounds" if j == 0 else None)
    ax.set_title("inputs (zero-hold)")
    ax.set_ylabel(_label("u", "/".join(dict.fromkeys(units))))


def _plot_errors(ax: Axes, t: np.ndarray, err: np.ndarray, names: Sequence[str], units: Sequence[str]) -> None:
    """Log scale: errors span many decades, and linear axes hide the small ones entirely."""
    largest = np.nanmax(np.abs(err)) if np.any(np.isfinite(err)) else 1.0
    floor = max(ERROR_FLOOR, largest * 10.0**-ERROR_DECADES)
    clipped = np.maximum(np.abs(err), floor)  # NaN stays NaN and is simply not drawn
    for i, name in enumerate(names):
        ax.plot(t, clipped[:, i], color=f"C{i}", lw=1.2, label=name)
    ax.set_yscale("log")
    ax.set_title("absolute error per state")
    ax.set_ylabel(_label("|error|", ", ".join(dict.fromkeys(units))))


def _finish(fig: Figure, axes: np.ndarray, title: str) -> Figure:
    """Shared cosmetics: grids, legends, bottom-row time labels and the optional title."""
    for ax in axes.flat:
        ax.grid(True, which="major", alpha=0.3)
        ax.legend(fontsize="small", loc="best")
    for ax in axes[-1]:
        ax.set_xlabel("t [s]")
    if title:
        fig.suptitle(title)
    return fig


def _comparison_figure(
    t: np.ndarray,
    first: tuple[str, np.ndarray, dict],
    second: tuple[str, np.ndarray, dict],
    u: np.ndarray,
    title: str,
    labels: Labels | None,
    u_bounds: tuple[Sequence[float], Sequence[float]] | None = None,
) -> Figure:
    """Two trajectories per state, their difference on a log axis, and the zero-hold inputs: the shared layout."""
    t = _time(t)
    state_names, state_units, input_names, input_units = labels or Labels()
    n, nx, nu = t.size, len(state_names), len(input_names)
    (name_a, x_a, style_a), (name_b, x_b, style_b) = first, second
    x_a, x_b = _as_2d(name_a, x_a, n, nx), _as_2d(name_b, x_b, n, nx)
    u_held = _held_inputs(t, u, nu)
    if u_bounds is not None and (len(u_bounds[0]) != nu or len(u_bounds[1]) != nu):
        raise ValueError(f"u_low and u_high need {nu} entries, got {len(u_bounds[0])} and {len(u_bounds[1])}")
    fig = Figure(figsize=TRACKING_FIGSIZE, layout="constrained")
    axes = fig.subplots(3, 2, sharex=True)
    for i, ax in enumerate(axes[:2].flat):
        ax.plot(t, x_a[:, i], **style_a)
        ax.plot(t, x_b[:, i], **style_b)
        ax.set_title(state_names[i])
        ax.set_ylabel(_label(state_names[i], state_units[i]))
    _plot_errors(axes[2, 0], t, x_b - x_a, state_names, state_units)
    _plot_inputs(axes[2, 1], t, u_held, input_names, input_units, *(u_bounds or (None, None)))
    return _finish(fig, axes, title)


def tracking_figure(
    t: np.ndarray,
    x_ref: np.ndarray,
    x: np.ndarray,
    u: np.ndarray,
    u_low: Sequence[float],
    u_high: Sequence[float],
    title: str = "",
    labels: Labels | None = None,
) -> Figure:
    """Closed-loop overview in one glance: does it track, how well (log error), and at what input effort."""
    reference = ("x_ref", x_ref, {"color": "k", "ls": "--", "lw": 1.2, "label": "reference"})
    actual = ("x", x, {"color": "C0", "lw": 1.4, "label": "actual"})
    return _comparison_figure(t, reference, actual, u, title, labels, (u_low, u_high))


def self_loop_figure(
    t: np.ndarray,
    x_plant: np.ndarray,
    x_pinn: np.ndarray,
    u: np.ndarray,
    title: str = "",
    labels: Labels | None = None,
) -> Figure:
    """Surrogate validation: where and how fast the PINN rollout drifts from the plant under the same inputs."""
    every = max(1, np.asarray(t).size // MAX_MARKERS)
    plant = ("x_plant", x_plant, {"color": "C0", "lw": 1.6, "label": "plant"})
    pinn_style = {"color": "C1", "ls": "--", "lw": 1.2, "marker": "o", "ms": 3.5, "markevery": every, "label": "PINN"}
    return _comparison_figure(t, plant, ("x_pinn", x_pinn, pinn_style), u, title, labels)


def scaling_figure(
    xs: Sequence[float],
    series: dict[str, Sequence[float]],
    xlabel: str,
    ylabel: str,
    title: str = "",
    logx: bool = True,
    logy: bool = True,
) -> Figure:
    """Benchmark scaling curves (e.g. OCP time vs horizon): log-log by default so power laws read as lines."""
    xs_arr = np.asarray(xs, dtype=float)
    fig = Figure(figsize=SCALING_FIGSIZE, layout="constrained")
    ax = fig.subplots()
    markers = "osD^vx*"
    for i, (name, ys) in enumerate(series.items()):
        ys_arr = np.asarray(ys, dtype=float)  # None becomes NaN: a missing point leaves a gap, not a crash
        if ys_arr.shape != xs_arr.shape:
            raise ValueError(f"series {name!r} has shape {ys_arr.shape}, xs has {xs_arr.shape}")
        ax.plot(xs_arr, ys_arr, marker=markers[i % len(markers)], lw=1.4, label=name)
    if logx:
        ax.set_xscale("log")
        ticks = np.unique(xs_arr[np.isfinite(xs_arr) & (xs_arr > 0)])
        if 0 < ticks.size <= MAX_XTICKS:  # horizons read as 5, 10, 20, not 5x10^0, 10^1, 2x10^1
            ax.set_xticks(ticks, labels=[f"{v:g}" for v in ticks])
            ax.xaxis.set_minor_formatter(NullFormatter())
    if logy:
        ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(True, which="both", alpha=0.3)
    if series:
        ax.legend(fontsize="small")
    if title:
        ax.set_title(title)
    return fig


def save_figure(fig: Figure, path: str | Path, dpi: int = DPI) -> Path:
    """PNG written atomically, so a watcher or a crash never sees a truncated image."""
    return atomic_write(path, lambda p: fig.savefig(p, format="png", dpi=dpi))


def arm_points(x: np.ndarray, link_lengths: tuple[float, float] = LINK_LENGTHS) -> np.ndarray:
    """Base, elbow and tip positions (N, 3, 2), alpha from the hanging-down vertical and beta relative to link 1."""
    x = np.atleast_2d(np.asarray(x, dtype=float))
    l1, l2 = link_lengths
    a, ab = x[:, 0], x[:, 0] + x[:, 1]
    elbow = l1 * np.stack([np.sin(a), -np.cos(a)], axis=-1)
    tip = elbow + l2 * np.stack([np.sin(ab), -np.cos(ab)], axis=-1)
    return np.stack([np.zeros_like(elbow), elbow, tip], axis=1)


def animate_arm(
    t: np.ndarray,
    x_ref: np.ndarray,
    x: np.ndarray,
    path: str | Path,
    fps: int = FPS,
    link_lengths: tuple[float, float] = LINK_LENGTHS,
    max_frames: int = MAX_FRAMES,
) -> Path:
    """A GIF shows tracking behaviour (overshoot, lag) that time plots of angles make hard to picture."""
    t = _time(t)
    n = t.size
    x_ref, x = np.asarray(x_ref, dtype=float), np.asarray(x, dtype=float)
    for name, a in (("x_ref", x_ref), ("x", x)):
        if a.ndim != 2 or a.shape[0] != n or a.shape[1] < 2:
            raise ValueError(f"{name} needs shape ({n}, >=2) for the joint angles, got {a.shape}")
    if max_frames < 1:
        raise ValueError(f"max_frames must be >= 1, got {max_frames}")
    frames = np.unique(np.linspace(0, n - 1, min(n, max_frames)).round().astype(int))
    p_ref, p = arm_points(x_ref, link_lengths), arm_points(x, link_lengths)

    fig = Figure(figsize=ARM_FIGSIZE, layout="constrained")
    FigureCanvasAgg(fig)  # the writer grabs RGBA buffers, which the bare base canvas cannot render
    ax = fig.subplots()
    reach = 1.1 * sum(link_lengths)
    ax.set(xlim=(-reach, reach), ylim=(-reach, reach), aspect="equal", xlabel="x [m]", ylabel="y [m]")
    ax.grid(True, alpha=0.3)
    ax.plot(p_ref[:, 2, 0], p_ref[:, 2, 1], color="0.6", lw=0.8, ls=":", label="reference tip path")
    # wide and faint underneath: still visible once the actual arm lies exactly on top of it
    (ref_line,) = ax.plot([], [], color="C2", ls="--", lw=7, marker="o", ms=10, alpha=0.35, label="reference")
    (trace,) = ax.plot([], [], color="C1", lw=1.0, label="tip trace")
    (arm_line,) = ax.plot([], [], color="C0", lw=3.5, marker="o", ms=7, mfc="k", mec="k", label="actual")
    label = ax.text(0.03, 0.96, "", transform=ax.transAxes, va="top", family="monospace")
    ax.legend(fontsize="small", loc="upper right")

    def draw(k: int) -> tuple:
        """One frame: sample index k of the full trajectory."""
        ref_line.set_data(p_ref[k, :, 0], p_ref[k, :, 1])
        arm_line.set_data(p[k, :, 0], p[k, :, 1])
        trace.set_data(p[: k + 1, 2, 0], p[: k + 1, 2, 1])
        label.set_text(f"t = {t[k]:6.2f} s")
        return ref_line, arm_line, trace, label

    anim = FuncAnimation(fig, draw, frames=frames.tolist(), blit=False, repeat=False)
    return atomic_write(path, lambda tmp: anim.save(tmp, writer=PillowWriter(fps=fps)), suffix=".gif")
