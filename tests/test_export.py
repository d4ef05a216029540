"""The exported flow map (pinnmpc.export) is the torch network: CasADi, C and ONNX against Surrogate.step."""

from __future__ import annotations

import ctypes
import json
import runpy
import subprocess
import sys
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
import torch

from pinnmpc.surrogate.checkpoint import CHECKPOINTS, load_surrogate, shipped
from pinnmpc.surrogate.export import (
    ExportCheckError,
    Tolerances,
    check_system,
    compile_c,
    export,
    held_out,
    trained_system,
)
from pinnmpc.systems import load_system
from tests.conftest import ROOT

POINTS = 300  # held-out points per comparison here; the export itself checks on conf/export.yaml's points


def _torch(ckpt: Path, x0: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x1, A, B of the torch network in float64."""
    s = load_surrogate(path=ckpt)
    x1, a, b = s.step_with_jacobian(torch.from_numpy(x0), torch.from_numpy(u))
    return x1.numpy(), a.numpy(), b.numpy()


@pytest.mark.parametrize("system", ["powercube", "planar3"])
def test_casadi_round_trip_matches_torch(system: str, tmp_path: Path) -> None:
    ckpt, out = shipped(system), tmp_path / "flow"
    info = export(ckpt, "casadi", out, points=1000, jacobian_points=50)
    assert info["max_abs_error"]["casadi"] <= 1e-12 and info["max_abs_error"]["casadi_jacobian"] <= 1e-10
    assert info["prior"] == (None if system == "powercube" else "frozen_arm")
    assert json.loads((out / "export.json").read_text())["max_abs_error"] == info["max_abs_error"]
    s = load_surrogate(path=ckpt)
    f = ca.Function.load(str(out / "flow.casadi"))
    x0, u = np.full(s.nx, 0.1), np.full(s.nu, 0.1)  # the check a user does, on plain vectors
    x1 = np.asarray(f(x0, u)).ravel()
    assert np.abs(x1 - s.step(torch.tensor(x0[None]), torch.tensor(u[None])).numpy()[0]).max() <= 1e-12
    x0, u = held_out(s, POINTS, seed=7)
    ref, a_ref, b_ref = _torch(ckpt, x0, u)
    assert np.abs(np.asarray(f.map(POINTS)(x0.T, u.T)).T - ref).max() <= 1e-12
    jac = ca.Function.load(str(out / "flow_jacobian.casadi"))
    for i in range(0, POINTS, 30):
        x1, a, b = (np.asarray(v) for v in jac(x0[i], u[i]))
        assert np.abs(x1.ravel() - ref[i]).max() <= 1e-12
        assert np.abs(a - a_ref[i]).max() <= 1e-10 and np.abs(b - b_ref[i]).max() <= 1e-10


def test_a_network_with_dead_units_exports_finite_jacobians() -> None:
    """fr3.pt's last hidden layer sits at silu pre-activations down to -1530, where 1 / (1 + exp(-a)) overflows: its
    value stays 0 but its derivative came out NaN in every entry of the exported Jacobian (the bench's CasADi peers
    then left the reference). The export's sigmoid is the tanh form, finite everywhere, and matches torch."""
    from pinnmpc.surrogate.casadi_network import casadi_flow

    s = load_surrogate(system="fr3")
    _, jac = casadi_flow(s)
    x0, u = held_out(s, 20, seed=3)
    ref, a_ref, b_ref = _torch(shipped("fr3"), x0, u)
    for i in range(0, 20, 5):
        x1, a, b = (np.asarray(v) for v in jac(x0[i], u[i]))
        assert np.isfinite(a).all() and np.isfinite(b).all()
        assert np.abs(x1.ravel() - ref[i]).max() <= 1e-12
        assert np.abs(a - a_ref[i]).max() <= 1e-9 and np.abs(b - b_ref[i]).max() <= 1e-9


@pytest.mark.parametrize("system", ["powercube", "planar3"])
def test_c_source_compiles_and_matches_torch(system: str, tmp_path: Path) -> None:
    ckpt, out = shipped(system), tmp_path / "c"
    info = export(ckpt, "c", out, points=1000, jacobian_points=50)
    assert sorted(info["files"]) == ["flow.c", "flow.h"] and info["max_abs_error"]["c"] <= 1e-12
    lib = compile_c(out / "flow.c", tmp_path / "libflow.so", opt="-O1")
    s = load_surrogate(path=ckpt)
    x0, u = held_out(s, 20, seed=3)
    ref, a_ref, b_ref = _torch(ckpt, x0, u)
    f, jac = ca.external("flow", str(lib)), ca.external("flow_jacobian", str(lib))
    assert np.abs(np.asarray(f.map(20)(x0.T, u.T)).T - ref).max() <= 1e-12
    _, a, b = (np.asarray(v) for v in jac(x0[0], u[0]))
    assert np.abs(a - a_ref[0]).max() <= 1e-10 and np.abs(b - b_ref[0]).max() <= 1e-10
    # the plain C API, as a user without CasADi calls it: flow(arg, res, iw, w, mem), work sizes from flow_work
    c = ctypes.CDLL(str(lib))
    vec, n = ctypes.POINTER(ctypes.c_double), ctypes.c_longlong
    sizes = [n() for _ in range(4)]
    assert c.flow_work(*(ctypes.byref(v) for v in sizes)) == 0
    sz_arg, sz_res, sz_iw, sz_w = (max(1, v.value) for v in sizes)
    x_in, u_in, x_out = (np.ascontiguousarray(v, dtype=np.float64) for v in (x0[1], u[1], np.zeros(s.nx)))
    args = (vec * sz_arg)(x_in.ctypes.data_as(vec), u_in.ctypes.data_as(vec))
    res = (vec * sz_res)(x_out.ctypes.data_as(vec))
    iw, w = (n * sz_iw)(), np.zeros(sz_w)
    assert c.flow(args, res, iw, w.ctypes.data_as(vec), 0) == 0
    assert np.abs(x_out - ref[1]).max() <= 1e-12


def test_onnx_matches_torch_in_float32(tmp_path: Path) -> None:
    pytest.importorskip("onnxruntime")
    import onnxruntime

    ckpt, out = shipped("powercube"), tmp_path / "onnx"
    info = export(ckpt, "onnx", out, points=2000)
    assert info["max_abs_error"]["onnx"] <= 1e-5
    s = load_surrogate(path=ckpt)
    x0, u = held_out(s, POINTS, seed=5)
    session = onnxruntime.InferenceSession(str(out / "flow.onnx"), providers=["CPUExecutionProvider"])
    x1 = session.run(None, {"x0": x0.astype(np.float32), "u": u.astype(np.float32)})[0]
    assert np.abs(x1 - _torch(ckpt, x0, u)[0]).max() <= 1e-5


def test_onnx_of_a_prior_network_is_refused_in_one_line(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="frozen-arm prior") as err:
        export(shipped("planar3"), "onnx", tmp_path / "onnx")
    assert "\n" not in str(err.value) and not (tmp_path / "onnx").exists()
    assert [p.name for p in tmp_path.iterdir()] == []  # no staging folder left behind


def test_a_failed_check_writes_nothing(tmp_path: Path) -> None:
    with pytest.raises(ExportCheckError, match="exceeds"):
        export(shipped("powercube"), "casadi", tmp_path / "out", points=50, tolerances=Tolerances(float64=1e-30))
    assert list(tmp_path.iterdir()) == []


def _cli(*args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess:
    """python -m pinnmpc.export as a user runs it."""
    return subprocess.run(
        [sys.executable, "-m", "pinnmpc.export", *args], capture_output=True, text=True, cwd=cwd, timeout=120
    )


def test_cli_exports_and_refuses_bad_input_in_one_line(tmp_path: Path) -> None:
    run = tmp_path / "run"
    ok = _cli(f"checkpoint={shipped('powercube')}", "format=casadi", f"out={tmp_path / 'flow'}", "points=500",
              f"hydra.run.dir={run}")  # fmt: skip
    assert ok.returncode == 0, ok.stderr[-2000:]
    assert "casadi" in ok.stdout and (tmp_path / "flow" / "flow.casadi").is_file()
    (tmp_path / "file").write_text("")
    cases = {
        "missing": (f"checkpoint={tmp_path / 'nope.pt'}", f"out={tmp_path / 'a'}"),
        "format": (f"checkpoint={shipped('powercube')}", "format=matlab", f"out={tmp_path / 'b'}"),
        "out_file": (f"checkpoint={shipped('powercube')}", f"out={tmp_path / 'file'}"),
    }
    for name, args in cases.items():
        r = _cli(*args, f"hydra.run.dir={tmp_path / name}")
        assert r.returncode == 2, (name, r.stderr[-2000:])
        assert len(r.stderr.strip().splitlines()) == 1 and "pinnmpc.export: error:" in r.stderr, (name, r.stderr)
        assert not (tmp_path / name).exists()
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists() and (tmp_path / "file").read_text() == ""


def test_an_explicit_system_refuses_a_checkpoint_of_another_in_one_line(tmp_path: Path) -> None:
    refused = _cli("system=planar3", f"checkpoint={shipped('powercube')}", f"out={tmp_path / 'flow'}",
                   f"hydra.run.dir={tmp_path / 'run'}")  # fmt: skip
    assert refused.returncode == 2, refused.stderr[-2000:]
    assert refused.stderr.strip().splitlines() == [
        f"pinnmpc.export: error: checkpoint={shipped('powercube')} is a network of powercube, not of system=planar3; "
        "expected a checkpoint of planar3, or no system= to export this one (HYDRA_FULL_ERROR=1 for a traceback)"
    ]
    assert not (tmp_path / "flow").exists() and not (tmp_path / "run").exists()
    # the checkpoint's own system, named or not, exports it
    for args in ([], ["system=planar3"]):
        ok = _cli(*args, f"checkpoint={shipped('planar3')}", f"out={tmp_path / 'ok'}", "points=50",
                  f"hydra.run.dir={tmp_path / 'ok_run'}")  # fmt: skip
        assert ok.returncode == 0 and (tmp_path / "ok" / "flow.casadi").is_file(), ok.stderr[-2000:]


def test_every_shipped_checkpoint_is_its_systems_and_no_other(tmp_path: Path) -> None:
    nets = {ckpt: load_surrogate(path=ckpt) for ckpt in sorted(CHECKPOINTS.glob("*.pt"))}
    names = {trained_system(net.meta) for net in nets.values()}
    assert {"powercube", "planar3", "panda"} <= names and None not in names
    systems = {name: load_system(name) for name in sorted(names)}
    for ckpt, net in nets.items():
        own = trained_system(net.meta)
        for name, system in systems.items():
            if name == own:
                check_system(net, ckpt, system)
            else:
                with pytest.raises(ValueError, match=f"is a network of {own}, not of system={name}"):
                    check_system(net, ckpt, system)
    # the same states, another arm (an FR3 network beside the Panda): its training config tells them apart
    net = load_surrogate(path=shipped("panda"))
    net.meta = {"config": {"system": {"dynamics": {"name": "fr3"}}}}
    with pytest.raises(ValueError, match="is a network of fr3, not of system=panda"):
        check_system(net, Path("fr3.pt"), systems["panda"])
    net.meta = {}  # no training record: the states alone decide
    check_system(net, Path("bare.pt"), systems["panda"])
    with pytest.raises(ValueError, match=r"is a network of another system \(states \['q_joint1'"):
        check_system(net, Path("bare.pt"), systems["planar3"])


def test_the_casadi_ocp_example_runs(capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sys, "argv", ["casadi_ocp_with_exported_flow.py"])  # exports planar3 itself
    runpy.run_path(str(ROOT / "examples" / "casadi_ocp_with_exported_flow.py"), run_name="__main__")
    said = capsys.readouterr().out
    assert "final joint-angle error" in said
    assert float(said.split("final joint-angle error ")[1].split()[0]) < 0.05
