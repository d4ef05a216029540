"""Real figures rendered into tmp_path: catches broken layouts, wrong scales and half-written files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from matplotlib.figure import Figure
from PIL import Image

from pinnmpc import load_system
from pinnmpc.util import plots

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
CUBE = load_system("powercube")
LABELS = plots.Labels.of(CUBE)
L1, L2 = CUBE.link_lengths


def _trajectory(n: int = 40) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A smooth reference, an offset 'actual' with exact zeros in one state, and sinusoidal inputs."""
    t = np.linspace(0.0, 2.0, n)
    x_ref = np.stack([np.sin(t), 0.5 * np.cos(t), np.cos(t), -0.5 * np.sin(t)], axis=1)
    x = x_ref + np.array([0.05, -0.02, 0.0, 0.1]) * np.exp(-t)[:, None]
    u = np.stack([np.sin(3 * t[:-1]), np.cos(2 * t[:-1])], axis=1)
    return t, x_ref, x, u


def _log_axes(fig: Figure) -> list:
    return [ax for ax in fig.axes if ax.get_yscale() == "log"]


def test_tracking_figure_layout() -> None:
    t, x_ref, x, u = _trajectory()
    x[:, 1] = x_ref[:, 1]  # an exact-zero error in beta
    fig = plots.tracking_figure(t, x_ref, x, u, (-2.0, -1.5), (2.0, 1.5), LABELS, title="tracking")
    assert isinstance(fig, Figure)
    assert len(fig.axes) == 6
    (err_ax,) = _log_axes(fig)
    assert len(err_ax.get_lines()) == 2  # joint angles only: rad and rad/s never share an axis
    ydata = np.concatenate([line.get_ydata() for line in err_ax.get_lines()])
    assert np.all(ydata >= plots.ERROR_FLOOR)  # the exact-zero beta error was clipped, not dropped
    steps = [line for ax in fig.axes for line in ax.get_lines() if line.get_drawstyle() == "steps-post"]
    assert len(steps) == 2 and all(len(line.get_xdata()) == t.size for line in steps)
    legend = [txt.get_text() for txt in fig.axes[-1].get_legend().get_texts()]
    assert legend == ["u1", "u1 bounds", "u2", "u2 bounds"]
    shared = plots.tracking_figure(t, x_ref, x, u, (-2.0, -2.0), (2.0, 2.0), LABELS)
    assert [txt.get_text() for txt in shared.axes[-1].get_legend().get_texts()] == ["u1", "u2", "bounds"]


def test_tracking_figure_rejects_bad_shapes() -> None:
    t, x_ref, x, u = _trajectory()
    with pytest.raises(ValueError, match="x_ref"):
        plots.tracking_figure(t, x_ref.T, x, u, (-1, -1), (1, 1), LABELS)
    with pytest.raises(ValueError, match="u must"):
        plots.tracking_figure(t, x_ref, x, u[:-3], (-1, -1), (1, 1), LABELS)


@pytest.mark.parametrize(("nq", "panels"), [(3, 8), (7, 4)])
def test_tracking_figure_any_number_of_joints(nq: int, panels: int) -> None:
    t = np.linspace(0.0, 1.0, 20)
    x_ref = np.sin(t[:, None] * np.arange(1, 2 * nq + 1))
    names = [f"q{i}" for i in range(nq)] + [f"v{i}" for i in range(nq)]
    labels = plots.Labels(names, ["rad"] * nq + ["rad/s"] * nq, [f"u{i}" for i in range(nq)], ["N m"] * nq)
    fig = plots.tracking_figure(t, x_ref, x_ref + 1e-3, np.zeros((19, nq)), [-1] * nq, [1] * nq, labels)
    assert len(fig.axes) == panels  # a panel per state up to 3 joints, else one for positions, one for velocities
    (err_ax,) = _log_axes(fig)
    assert len(err_ax.get_lines()) == nq


def test_self_loop_figure_layout() -> None:
    t, x_plant, x_pinn, u = _trajectory()
    fig = plots.self_loop_figure(t, x_plant, x_pinn, u, LABELS, title="self loop")
    assert isinstance(fig, Figure)
    assert len(fig.axes) == 6
    assert len(_log_axes(fig)) == 1


def test_scaling_figure() -> None:
    fig = plots.scaling_figure(
        [5, 10, 20, 40], {"pinn": [1e-3, 2e-3, 4e-3, 9e-3], "rk4": [2e-3, 5e-3, None, 3e-2]}, "horizon", "time [s]"
    )
    (ax,) = fig.axes
    assert ax.get_xscale() == "log" and ax.get_yscale() == "log"
    assert len(ax.get_lines()) == 2
    lin = plots.scaling_figure([1, 2], {"a": [1, 2]}, "x", "y", logx=False, logy=False)
    assert lin.axes[0].get_yscale() == "linear"


def test_save_figure_writes_png_atomically(tmp_path: Path) -> None:
    t, x_ref, x, u = _trajectory()
    fig = plots.tracking_figure(t, x_ref, x, u, (-2.0, -1.5), (2.0, 1.5), LABELS)
    out = plots.save_figure(fig, tmp_path / "sub" / "tracking.png", dpi=60)
    assert out == tmp_path / "sub" / "tracking.png"
    data = out.read_bytes()
    assert data[:8] == PNG_MAGIC and len(data) > 10_000
    with Image.open(out) as img:
        assert img.size == (600, 540)  # 10 x 9 inches at 60 dpi (three rows of panels)
    assert [p.name for p in out.parent.iterdir()] == ["tracking.png"]


def test_save_figure_failure_leaves_nothing(tmp_path: Path) -> None:
    fig = plots.scaling_figure([1, 2], {"a": [1, 2]}, "x", "y")
    with pytest.raises(ValueError):
        plots.save_figure(fig, tmp_path / "bad.png", dpi=-5)
    assert list(tmp_path.iterdir()) == []


def test_powercube_kinematics_geometry() -> None:
    q = np.array([[0.0, 0.0], [np.pi / 2, 0.0], [np.pi / 2, -np.pi / 2]])
    pts = CUBE.kinematics(q)
    assert pts.shape == (3, 3, 3)
    np.testing.assert_allclose(pts[:, 0], 0.0)
    np.testing.assert_allclose(pts[0, 2, :2], [0.0, -(L1 + L2)], atol=1e-12)
    np.testing.assert_allclose(pts[1, 1, :2], [L1, 0.0], atol=1e-12)
    np.testing.assert_allclose(pts[2, 2, :2], [L1, -L2], atol=1e-12)  # beta is relative to link 1


@pytest.mark.parametrize(("max_frames", "expected"), [(300, 12), (5, 5)])
def test_animate_arm_writes_gif(tmp_path: Path, max_frames: int, expected: int) -> None:
    t, x_ref, x, _ = _trajectory(12)
    p_ref, p = CUBE.kinematics(x_ref[:, :2]), CUBE.kinematics(x[:, :2])
    err = np.abs(x - x_ref)[:, :2].max(axis=1)
    out = plots.animate_arm(t, p_ref, p, tmp_path / "arm.gif", title="t", error=err, fps=5, max_frames=max_frames)
    assert out.read_bytes()[:4] == b"GIF8"
    with Image.open(out) as img:
        assert img.n_frames == expected
    assert [p.name for p in tmp_path.iterdir()] == ["arm.gif"]


def test_animate_arm_draws_in_3d_when_not_planar(tmp_path: Path) -> None:
    t = np.linspace(0.0, 1.0, 4)
    pts = np.zeros((4, 3, 3))
    pts[:, 1] = [0.0, 0.0, 0.3]
    pts[:, 2] = np.stack([0.2 * t, 0.1 * t, 0.5 + 0 * t], axis=1)
    assert plots._plane(pts) is None
    out = plots.animate_arm(t, pts, pts, tmp_path / "arm3d.gif")
    with Image.open(out) as img:
        assert img.n_frames == 4


def test_an_arm_in_a_vertical_plane_is_drawn_in_that_plane() -> None:
    q = np.array([[0.0, 0.0], [np.pi / 2, 0.0], [np.pi / 2, -np.pi / 2]])
    in_xy = CUBE.kinematics(q)  # the PowerCube's drawing lies in the x-y plane
    in_xz = in_xy[..., [0, 2, 1]]  # the same arm turned into the x-z plane (a URDF arm whose joints turn about y)
    assert (
        plots._plane(in_xy) == (0, 1)
        and plots._plane(in_xz) == (0, 2)
        and plots._plane(in_xy[..., [2, 0, 1]]) == (1, 2)
    )
