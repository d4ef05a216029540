"""The closed loop as a library, part by part with explicit arguments: what examples/minimal_closed_loop.py shows."""

from __future__ import annotations

import runpy

import numpy as np

from pinnmpc import load_surrogate, load_system
from pinnmpc.controller.build import build_nmpc
from pinnmpc.plant import ScipyPlant
from pinnmpc.references import Reference
from pinnmpc.simulation import LoopResult, run_loop
from tests.conftest import ROOT


def test_a_closed_loop_from_its_parts_tracks_the_reference():
    system = load_system("planar3")
    flow = load_surrogate(system="planar3")
    controller = build_nmpc({"horizon": 5, "Q": [1, 1, 1, 0, 0, 0], "R": [1e-8, 1e-7, 1e-6]}, flow, system)
    plant = ScipyPlant(system, flow.tau)
    t = np.arange(0.0, 3.0, flow.tau)
    q = 0.3 * np.sin(np.outer(t, [0.5, 0.8, 1.1]))
    reference = Reference(t, np.hstack([q, np.gradient(q, t, axis=0)]), "sine")
    result = run_loop(controller, plant, reference, max_steps=20, progress=False)
    assert isinstance(result, LoopResult) and result.status == "ok"
    assert result.x.shape == (21, 6) and result.u.shape == (20, 3) and np.isfinite(result.u).all()
    error = np.abs(result.x[:, :3] - reference.x[:21, :3]).max()
    assert error < 1e-2, error  # on the path it starts on


def test_the_minimal_example_runs():
    out = runpy.run_path(str(ROOT / "examples" / "minimal_closed_loop.py"), run_name="__main__")
    assert out["result"].status == "ok"
