"""Reusable matplotlib figures: built on bare Figure objects so library code never touches pyplot's global state."""

from __future__ import annotations

import logging
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from matplotlib.animation import FuncAnimation, PillowWriter
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import NullFormatter
from tqdm.auto import tqdm

from pinnmpc.util.io import atomic_write

# Display defaults only: nothing here is a model parameter.
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

logging.getLogger("matplotlib.animation").setLevel(logging.WARNING)  # its INFO lines name the writer, nothing more


MAX_JOINT_PANELS = 3  # up to this many joints get a panel per state; more share one position and one velocity panel


class Labels(NamedTuple):
    """Names and units of states and inputs: every panel is labelled from the system."""

    state_names: Sequence[str]
    state_units: Sequence[str]
    input_names: Sequence[str]
    input_units: Sequence[str]

    @classmethod
    def of(cls, system: Any) -> Labels:
        """Labels of a System (anything with state/input names and units)."""
        return cls(system.state_names, system.state_units, system.input_names, system.input_units)


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


def _plot_errors(
    ax: Axes, t: np.ndarray, err: np.ndarray, names: Sequence[str], units: Sequence[str], title: str
) -> None:
    """Log scale: errors span many decades, and linear axes hide the small ones entirely."""
    largest = np.nanmax(np.abs(err)) if np.any(np.isfinite(err)) else 1.0
    floor = max(ERROR_FLOOR, largest * 10.0**-ERROR_DECADES)
    clipped = np.maximum(np.abs(err), floor)  # NaN stays NaN and is simply not drawn
    for i, name in enumerate(names):
        ax.plot(t, clipped[:, i], color=f"C{i}", lw=1.2, label=name)
    ax.set_yscale("log")
    ax.set_title(title)
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
    labels: Labels,
    u_bounds: tuple[Sequence[float], Sequence[float]] | None = None,
) -> Figure:
    """Two trajectories per state, their difference on a log axis, and the zero-hold inputs: the shared layout."""
    t = _time(t)
    state_names, state_units, input_names, input_units = labels
    n, nx, nu = t.size, len(state_names), len(input_names)
    (name_a, x_a, style_a), (name_b, x_b, style_b) = first, second
    x_a, x_b = _as_2d(name_a, x_a, n, nx), _as_2d(name_b, x_b, n, nx)
    u_held = _held_inputs(t, u, nu)
    if u_bounds is not None and (len(u_bounds[0]) != nu or len(u_bounds[1]) != nu):
        raise ValueError(f"u_low and u_high need {nu} entries, got {len(u_bounds[0])} and {len(u_bounds[1])}")
    nq = nx // 2
    groups = [[i] for i in range(nx)] if nq <= MAX_JOINT_PANELS else [list(range(nq)), list(range(nq, nx))]
    rows = len(groups) // 2 + 1
    fig = Figure(figsize=(TRACKING_FIGSIZE[0], 3.0 * rows), layout="constrained")
    axes = fig.subplots(rows, 2, sharex=True, squeeze=False)
    panels = [axes[r, c] for c in range(2) for r in range(rows - 1)]  # positions down the left, velocities right
    for ax, group in zip(panels, groups):
        for k, i in enumerate(group):
            many = len(group) > 1
            ax.plot(t, x_a[:, i], **{**style_a, **({"color": f"C{k}", "label": None} if many else {})})
            ax.plot(t, x_b[:, i], **{**style_b, **({"color": f"C{k}", "label": state_names[i]} if many else {})})
        ax.set_title(state_names[group[0]] if len(group) == 1 else f"{'positions' if group[0] < nq else 'velocities'}")
        ax.set_ylabel(_label(state_names[group[0]] if len(group) == 1 else "x", state_units[group[0]]))
    err = np.abs(x_b - x_a)
    _plot_errors(axes[-1, 0], t, err[:, :nq], state_names[:nq], state_units[:nq], "position error")
    _plot_inputs(axes[-1, 1], t, u_held, input_names, input_units, *(u_bounds or (None, None)))
    return _finish(fig, axes, title)


def tracking_figure(
    t: np.ndarray,
    x_ref: np.ndarray,
    x: np.ndarray,
    u: np.ndarray,
    u_low: Sequence[float],
    u_high: Sequence[float],
    labels: Labels,
    title: str = "",
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
    labels: Labels,
    title: str = "",
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


def residual_figure(t_edges: np.ndarray, rms: np.ndarray, state_names: Sequence[str], title: str = "") -> Figure:
    """Heat map of an RMS residual per time bin (rows) and state (columns), log colours, each cell labelled."""
    rms = _as_2d("rms", np.asarray(rms, dtype=float), len(t_edges) - 1, len(state_names))
    shown = np.clip(rms, max(ERROR_FLOOR, rms.max() * 10.0**-ERROR_DECADES), None)
    fig = Figure(figsize=(max(5.0, 0.75 * len(state_names) + 2.5), 0.45 * len(rms) + 2.0), layout="constrained")
    ax = fig.subplots()
    image = ax.imshow(np.log10(shown), aspect="auto", cmap="viridis")
    level = np.log10(shown)
    bright = level.min() + 0.7 * np.ptp(level)  # cells this far up the colour map are light: dark text on them
    for (i, j), v in np.ndenumerate(rms):
        color = "k" if level[i, j] > bright else "w"
        ax.text(j, i, f"{v:.1e}", ha="center", va="center", fontsize="x-small", color=color)
    ax.set_xticks(range(len(state_names)), labels=list(state_names), rotation=45, ha="right")
    ms = 1e3 * np.asarray(t_edges, dtype=float)
    ax.set_yticks(range(len(rms)), labels=[f"{a:.3g}-{b:.3g}" for a, b in zip(ms[:-1], ms[1:])])
    ax.set_ylabel("t in the step, ms")
    fig.colorbar(image, ax=ax, label="log10 RMS residual (network units)")
    if title:
        ax.set_title(title, fontsize="small")
    return fig


def basis_figure(
    misfit: Sequence[Sequence[float]],
    labels: Sequence[str],
    state_names: Sequence[str],
    targets: Sequence[float | None] | None = None,
    title: str = "",
    ylabel: str = "RMS misfit over the step (state units)",
    legend: str = "time_basis, s",
) -> Figure:
    """One line per time basis (or per error measured): its misfit per state (log scale), the basis under test
    first; the system's one-step targets as marks, where it has them."""
    fig = Figure(figsize=SCALING_FIGSIZE, layout="constrained")
    ax = fig.subplots()
    for values, label in zip(misfit, labels):
        ax.semilogy(np.clip(np.asarray(values, dtype=float), ERROR_FLOOR, None), "o-", label=label)
    if targets is not None:
        given = [(i, v) for i, v in enumerate(targets) if v is not None]
        ax.plot([i for i, _ in given], [v for _, v in given], "k_", markersize=20, label="one-step target")
    ax.set_xticks(range(len(state_names)), labels=list(state_names), rotation=45, ha="right")
    ax.set_ylabel(ylabel)
    ax.legend(title=legend, fontsize="x-small")
    if title:
        ax.set_title(title, fontsize="small")
    return fig


def frontier_figure(points: dict[str, tuple[float, float]], xlabel: str, ylabel: str, title: str = "") -> Figure:
    """Controllers as points (cost, error) on log-log axes: what each buys and pays, the frontier down and left."""
    fig = Figure(figsize=(7.5, 6.5), layout="constrained")
    ax = fig.subplots()
    markers = "osD^v<>pPX*hH"
    for i, (name, (x, y)) in enumerate(points.items()):
        ax.plot([x], [y], marker=markers[i % len(markers)], ls="none", ms=8, label=name)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(True, which="both", alpha=0.3)
    if points:  # below the axes: the labels are long
        ax.legend(fontsize="x-small", loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=1)
    if title:
        ax.set_title(title, fontsize="medium")
    return fig


def save_figure(fig: Figure, path: str | Path, dpi: int = DPI) -> Path:
    """PNG written atomically, so a watcher or a crash never sees a truncated image."""
    return atomic_write(path, lambda p: fig.savefig(p, format="png", dpi=dpi))


def _plane(points: np.ndarray) -> tuple[int, int] | None:
    """The two axes an arm moves in when every drawn point keeps one coordinate (x-y, x-z or y-z plane): then a
    2-D drawing says everything; None for an arm that moves in 3-D."""
    flat = [axis for axis in (2, 1, 0) if np.ptp(points[..., axis]) < 1e-9]
    return None if not flat else tuple(a for a in (0, 1, 2) if a != flat[0])  # type: ignore[return-value]


def animate_arm(
    t: np.ndarray,
    p_ref: np.ndarray,
    p: np.ndarray,
    path: str | Path,
    title: str = "",
    error: np.ndarray | None = None,
    fps: int = FPS,
    max_frames: int = MAX_FRAMES,
    progress: bool = False,
) -> Path:
    """A GIF shows tracking behaviour (overshoot, lag) that time plots of angles make hard to picture.

    p_ref and p are the arm's drawn points (N, k, 3) from System.kinematics, base first and tip last; error is
    the largest joint-angle error per sample, shown as a readout. Frames are subsampled to at most max_frames
    and played at fps, so the title states the playback speed against real time; progress shows a bar over the
    frames (rendering takes tens of seconds)."""
    t = _time(t)
    n = t.size
    p_ref, p = np.asarray(p_ref, dtype=float), np.asarray(p, dtype=float)
    for name, a in (("p_ref", p_ref), ("p", p)):
        if a.ndim != 3 or a.shape[0] != n or a.shape[2] != 3:
            raise ValueError(f"{name} needs shape ({n}, points, 3), got {a.shape}")
    if max_frames < 1:
        raise ValueError(f"max_frames must be >= 1, got {max_frames}")
    frames = np.unique(np.linspace(0, n - 1, min(n, max_frames)).round().astype(int))
    speed = (t[-1] - t[0]) / max(len(frames) / fps, 1e-9)
    plane = _plane(np.concatenate([p_ref, p]))
    planar = plane is not None
    fig = Figure(figsize=ARM_FIGSIZE, layout="constrained")
    FigureCanvasAgg(fig)  # the writer grabs RGBA buffers, which the bare base canvas cannot render
    reach = 1.1 * float(np.max(np.linalg.norm(np.concatenate([p_ref, p]), axis=-1)))
    if plane is not None:
        ax = fig.subplots()
        names = [f"{'xyz'[d]} [m]" for d in plane]
        ax.set(xlim=(-reach, reach), ylim=(-reach, reach), aspect="equal", xlabel=names[0], ylabel=names[1])
        dims: tuple[int, ...] = plane
    else:
        ax = fig.add_subplot(projection="3d")
        z_low = min(0.0, float(np.concatenate([p_ref, p])[..., 2].min()))  # a base at the bottom, unless it hangs
        ax.set(xlim=(-reach, reach), ylim=(-reach, reach), zlim=(z_low, z_low + 2 * reach), xlabel="x", ylabel="y")
        ax.set_zlabel("z")
        dims = (0, 1, 2)
    ax.grid(True, alpha=0.3)
    tip_ref = [p_ref[:, -1, d] for d in dims]
    ax.plot(*tip_ref, color="0.6", lw=0.8, ls=":", label="reference tip path")
    # wide and faint underneath: still visible once the actual arm lies exactly on top of it
    (ref_line,) = ax.plot(
        *[[]] * len(dims), color="C2", ls="--", lw=7, marker="o", ms=10, alpha=0.35, label="reference"
    )
    (trace,) = ax.plot(*[[]] * len(dims), color="C1", lw=1.0, label="tip trace")
    (arm_line,) = ax.plot(*[[]] * len(dims), color="C0", lw=3.5, marker="o", ms=6, mfc="k", mec="k", label="actual")
    text = ax.text if planar else ax.text2D  # a 3-D axes places fixed text with text2D
    label = text(0.02, 0.98, "", transform=ax.transAxes, va="top", family="monospace", fontsize="small")
    playback = f"playback {speed:.1f}x real time"
    fig.suptitle(f"{title}\n{playback}" if title else playback, fontsize="medium")
    ax.legend(fontsize="small", loc="upper right")

    def put(line: Any, pts: np.ndarray) -> None:
        """Set a 2-D or 3-D line's data."""
        line.set_data(pts[:, dims[0]], pts[:, dims[1]])
        if not planar:
            line.set_3d_properties(pts[:, 2])

    def draw(k: int) -> tuple:
        """One frame: sample index k of the full trajectory."""
        put(ref_line, p_ref[k])
        put(arm_line, p[k])
        put(trace, p[: k + 1, -1])
        readout = f"t = {t[k]:6.2f} s"
        if error is not None:
            readout += f"\nmax |angle error| {error[k]:.1e} rad"
        label.set_text(readout)
        return ref_line, arm_line, trace, label

    anim = FuncAnimation(fig, draw, frames=frames.tolist(), blit=False, repeat=False)
    with tqdm(total=len(frames), desc=Path(path).name, unit="frame", disable=not progress, file=sys.stderr) as bar:
        tick = lambda *_: bar.update(1)  # noqa: E731
        return atomic_write(
            path, lambda tmp: anim.save(tmp, writer=PillowWriter(fps=fps), progress_callback=tick), suffix=".gif"
        )
