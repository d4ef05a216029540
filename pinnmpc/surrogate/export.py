"""Export a trained flow map x(tau) = f(x0, u) and its Jacobian for use outside pinnmpc: a serialised CasADi
function, C source from CasADi's code generator, or an ONNX graph. Every export is checked against the torch
network on held-out points before anything is written, and lands in its folder all at once or not at all.
run_export is the job `python -m pinnmpc.export` runs."""

from __future__ import annotations

import copy
import json
import math
import os
import subprocess
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np
import torch
from omegaconf import DictConfig
from torch import Tensor, nn

from pinnmpc.surrogate.casadi_network import casadi_flow
from pinnmpc.surrogate.checkpoint import Surrogate, load_surrogate, shipped
from pinnmpc.surrogate.export_settings import validate_export
from pinnmpc.systems.base import System
from pinnmpc.systems.settings import job_system

FORMATS = ("casadi", "c", "onnx")
FLOAT64_FORMATS = ("casadi", "c")  # evaluated in float64; onnx runs in float32
META_KEYS = ("status", "epochs", "best_val_rmse_position", "training_time_s", "command_delay")  # the checkpoint's meta
#   worth keeping; command_delay: its controller splits each period there (pinnmpc.surrogate.delayed_command), while
#   the exported flow is the network's over the whole period under a held input
FLOW_NAME = "flow"  # the exported functions: flow(x0, u) -> x1 and flow_jacobian(x0, u) -> (x1, A, B)


class ExportCheckError(FloatingPointError):
    """The exported function disagrees with the torch network beyond the tolerance: a failed run, not bad input."""


@dataclass(frozen=True)
class Tolerances:
    """Largest absolute errors an export may have against the torch network (float64 reference)."""

    float64: float = 1e-12  # casadi and c: the same float64 arithmetic in another order
    float32: float = 1e-5  # onnx: float32 weights and arithmetic
    jacobian: float = 1e-10  # dx1/d(x0, u) of casadi and c against the torch forward-mode Jacobian


def held_out(surrogate: Surrogate, points: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Points uniform in the network's training box (x0 (points, nx), u (points, nu)), seeded."""
    rng = np.random.default_rng(seed)
    x0 = rng.uniform(surrogate.state_box.low, surrogate.state_box.high, (points, surrogate.nx))
    u = rng.uniform(surrogate.input_box.low, surrogate.input_box.high, (points, surrogate.nu))
    return x0, u


def _batched(f: ca.Function, x0: np.ndarray, u: np.ndarray) -> list[np.ndarray]:
    """A CasADi function of column vectors over rows: each output as (points, rows, cols)."""
    n = len(x0)
    out = f.map(n)(x0.T, u.T)
    out = out if isinstance(out, (list, tuple)) else [out]
    shapes = [(f.size1_out(i), f.size2_out(i)) for i in range(f.n_out())]
    return [np.asarray(o).reshape(r, n, c).transpose(1, 0, 2) for o, (r, c) in zip(out, shapes)]


def _errors(
    f: ca.Function, jac: ca.Function, surrogate: Surrogate, x0: np.ndarray, u: np.ndarray, jac_points: int
) -> tuple[float, float]:
    """Max absolute error of f on all points and of jac's (A, B) on the first jac_points, against torch."""
    ref = surrogate.step(torch.from_numpy(x0), torch.from_numpy(u)).numpy()
    value = float(np.abs(_batched(f, x0, u)[0][..., 0] - ref).max())
    xs, us = x0[:jac_points], u[:jac_points]
    _, a_ref, b_ref = surrogate.step_with_jacobian(torch.from_numpy(xs), torch.from_numpy(us))
    _, a, b = _batched(jac, xs, us)
    return value, float(max(np.abs(a - a_ref.numpy()).max(), np.abs(b - b_ref.numpy()).max()))


class FlowModule(nn.Module):
    """step(x0, u) as a plain module (tau fixed), for torch.onnx.export."""

    def __init__(self, surrogate: Surrogate, dtype: torch.dtype = torch.float32) -> None:
        super().__init__()
        self.model = copy.deepcopy(surrogate.model).to(dtype)  # the float64 original stays the reference
        self.tau = surrogate.tau

    def forward(self, x0: Tensor, u: Tensor) -> Tensor:
        """x(tau) for x0 (batch, nx), u (batch, nu)."""
        return self.model(torch.full_like(x0[..., :1], self.tau), x0, u)


def _write_casadi(f: ca.Function, jac: ca.Function, folder: Path) -> list[str]:
    """flow.casadi and flow_jacobian.casadi (Function.save)."""
    f.save(str(folder / f"{FLOW_NAME}.casadi"))
    jac.save(str(folder / f"{FLOW_NAME}_jacobian.casadi"))
    return [f"{FLOW_NAME}.casadi", f"{FLOW_NAME}_jacobian.casadi"]


def _write_c(f: ca.Function, jac: ca.Function, folder: Path) -> list[str]:
    """flow.c and flow.h: both functions, CasADi's calling convention (casadi.external or the header's API)."""
    gen = ca.CodeGenerator(f"{FLOW_NAME}.c", {"with_header": True})
    gen.add(f)
    gen.add(jac)
    gen.generate(f"{folder}/")
    return [f"{FLOW_NAME}.c", f"{FLOW_NAME}.h"]


def compile_c(source: Path, library: Path, compiler: str = "gcc", opt: str = "-O1") -> Path:
    """Build a shared library from exported C source (what a user does with flow.c); OSError when it fails."""
    cmd = [compiler, opt, "-shared", "-fPIC", str(source), "-o", str(library), "-lm"]
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    except FileNotFoundError:
        raise OSError(f"the C compiler {compiler!r} was not found; format=c needs one to check the source") from None
    if done.returncode:
        said = done.stderr.strip().splitlines()
        raise OSError(f"compiling {source.name} failed: {said[-1] if said else done.returncode}")
    return library


def _check_c(folder: Path, scratch: Path, compiler: str, opt: str) -> tuple[ca.Function, ca.Function]:
    """The generated source compiled and loaded back, so that what is checked is what the user compiles."""
    lib = compile_c(folder / f"{FLOW_NAME}.c", scratch / f"lib{FLOW_NAME}.so", compiler, opt)
    return ca.external(FLOW_NAME, str(lib)), ca.external(f"{FLOW_NAME}_jacobian", str(lib))


def _write_onnx(surrogate: Surrogate, folder: Path, opset: int) -> list[str]:
    """flow.onnx: inputs x0 (batch, nx), u (batch, nu), output x1, float32, a dynamic batch."""
    if surrogate.model.prior is not None:
        raise ValueError(
            "format=onnx cannot export this network: its frozen-arm prior is built from CasADi (and a matrix "
            "exponential ONNX lacks); use format=casadi or format=c"
        )
    module = FlowModule(surrogate).eval()
    example = (torch.zeros(2, surrogate.nx), torch.zeros(2, surrogate.nu))
    batch = {0: "batch"}
    with warnings.catch_warnings():  # the tracer's notes on Python branches over fixed sizes (periodic, sums)
        warnings.simplefilter("ignore", torch.jit.TracerWarning)
        torch.onnx.export(
            module, example, str(folder / f"{FLOW_NAME}.onnx"), input_names=["x0", "u"], output_names=["x1"],
            dynamic_axes={"x0": batch, "u": batch, "x1": batch}, opset_version=opset, dynamo=False,
        )  # fmt: skip
    return [f"{FLOW_NAME}.onnx"]


def _onnx_error(folder: Path, surrogate: Surrogate, x0: np.ndarray, u: np.ndarray) -> float:
    """Max absolute error of the ONNX graph under onnxruntime against the float64 torch network."""
    import onnxruntime

    session = onnxruntime.InferenceSession(str(folder / f"{FLOW_NAME}.onnx"), providers=["CPUExecutionProvider"])
    x1 = session.run(["x1"], {"x0": x0.astype(np.float32), "u": u.astype(np.float32)})[0]
    ref = surrogate.step(torch.from_numpy(x0), torch.from_numpy(u)).numpy()
    return float(np.abs(x1.astype(np.float64) - ref).max())


def summary(surrogate: Surrogate, checkpoint: Path) -> dict[str, Any]:
    """What export.json says about the network: where it came from and what it maps."""
    cfg = surrogate.model.config
    meta = {k: surrogate.meta[k] for k in META_KEYS if k in surrogate.meta}
    prior = cfg.get("prior")
    return {
        "checkpoint": str(checkpoint),
        "tau": surrogate.tau,
        "state_names": list(surrogate.state_names),
        "input_names": list(surrogate.input_names),
        "state_box": [list(surrogate.state_box.low), list(surrogate.state_box.high)],
        "input_box": [list(surrogate.input_box.low), list(surrogate.input_box.high)],
        "hidden": cfg["hidden"],
        "activation": cfg["activation"],
        "prior": None if prior is None else prior["kind"],
        "meta": meta,
    }


def _out_folder(out: Path) -> Path:
    """The folder to write into: refused in one line when it is a file or cannot be made."""
    out = Path(os.path.abspath(out))
    if out.exists() and not out.is_dir():
        raise ValueError(f"out={out} is a file; expected a folder (new or existing) for the exported files")
    if not out.parent.is_dir():
        raise ValueError(f"out={out}: its parent folder {out.parent} does not exist; expected an existing parent")
    return out


def _publish(staged: Path, out: Path) -> None:
    """Move the staged files into out: the whole folder at once where out is new, else each file atomically."""
    if not out.exists():
        staged.rename(out)
        return
    for entry in staged.iterdir():
        os.replace(entry, out / entry.name)


def export(
    checkpoint: str | Path,
    fmt: str,
    out: str | Path,
    points: int = 10_000,
    jacobian_points: int = 200,
    seed: int = 0,
    tolerances: Tolerances = Tolerances(),
    compiler: str = "gcc",
    opt: str = "-O1",
    opset: int = 17,
    system: System | None = None,
) -> dict[str, Any]:
    """Write the flow map of checkpoint in format fmt into out, after checking it on held-out points; returns what
    export.json holds. ValueError for bad input (nothing written; a checkpoint of another system than `system`, where
    one is given), ExportCheckError when the check fails."""
    if fmt not in FORMATS:
        raise ValueError(f"format={fmt!r}: expected one of {list(FORMATS)}")
    out, checkpoint = _out_folder(Path(out)), Path(checkpoint)
    surrogate = load_surrogate(path=checkpoint)
    if system is not None:
        check_system(surrogate, checkpoint, system)
    x0, u = held_out(surrogate, points, seed)
    info = {**summary(surrogate, checkpoint.resolve()), "format": fmt, "out": str(out), "points": points, "seed": seed}
    with tempfile.TemporaryDirectory(dir=out.parent, prefix=f".{out.name}.") as tmp:
        staged, scratch = Path(tmp) / "out", Path(tmp) / "scratch"
        staged.mkdir()
        scratch.mkdir()
        if fmt == "onnx":
            files = _write_onnx(surrogate, staged, opset)
            errors = {"onnx": _onnx_error(staged, surrogate, x0, u)}
            limit = tolerances.float32
        else:
            f, jac = casadi_flow(surrogate, FLOW_NAME)
            files = (_write_casadi if fmt == "casadi" else _write_c)(f, jac, staged)
            if fmt == "casadi":  # what a user loads, not what was built
                f = ca.Function.load(str(staged / f"{FLOW_NAME}.casadi"))
                jac = ca.Function.load(str(staged / f"{FLOW_NAME}_jacobian.casadi"))
            else:
                f, jac = _check_c(staged, scratch, compiler, opt)
            value, jacobian = _errors(f, jac, surrogate, x0, u, min(jacobian_points, points))
            errors = {fmt: value, f"{fmt}_jacobian": jacobian}
            limit = tolerances.float64
        info |= {"files": files, "max_abs_error": errors, "tolerance": limit, "jacobian_tolerance": tolerances.jacobian}
        worst = errors[fmt]
        if not (math.isfinite(worst) and worst <= limit):
            raise ExportCheckError(
                f"format={fmt}: max abs error {worst:.2e} against the torch network on {points} held-out points "
                f"exceeds {limit:.0e}; nothing written"
            )
        jac_error = errors.get(f"{fmt}_jacobian", 0.0)
        if not (math.isfinite(jac_error) and jac_error <= tolerances.jacobian):
            raise ExportCheckError(
                f"format={fmt}: Jacobian max abs error {jac_error:.2e} against the torch network exceeds "
                f"{tolerances.jacobian:.0e}; nothing written"
            )
        (staged / "export.json").write_text(json.dumps(info, indent=2) + "\n")
        _publish(staged, out)
    return info


def trained_system(meta: dict[str, Any] | None) -> str | None:
    """The name of the system a network was trained for, from the training config in its meta (None: no record)."""
    node = ((meta or {}).get("config") or {}).get("system")
    if not isinstance(node, dict):
        return None
    if isinstance(node.get("dynamics"), dict):  # conf/system/<name>.yaml; older networks kept the System node alone
        node = node["dynamics"]
    name = node.get("name") or str(node.get("_target_", "")).rsplit(".", 1)[-1].lower()
    return str(name) if name else None


def check_system(surrogate: Surrogate, checkpoint: Path, system: System) -> None:
    """A checkpoint of another system than an explicit system=: refused, since its files would carry that network
    under this arm's name."""
    trained = trained_system(surrogate.meta)
    if tuple(surrogate.state_names) == tuple(system.state_names) and trained in (None, system.name):
        return
    what = trained or f"another system (states {list(surrogate.state_names)})"
    raise ValueError(
        f"checkpoint={checkpoint} is a network of {what}, not of system={system.name}; expected a checkpoint of "
        f"{system.name}, or no system= to export this one"
    )


def run_export(cfg: DictConfig, run_dir: Path, system_given: bool = False) -> dict[str, Any]:
    """Export, check and write the files; the returned dict is the export.json written next to them. With
    system_given (system= on the command line) the checkpoint must be a network of that system."""
    system: System = job_system(cfg, validate_export)
    checkpoint = shipped(system.name) if cfg.checkpoint is None else Path(cfg.checkpoint)
    out = run_dir if cfg.out is None else Path(cfg.out)
    tol = cfg.tolerance
    return export(
        checkpoint, cfg.format, out, points=cfg.points, jacobian_points=cfg.jacobian_points, seed=cfg.seed,
        tolerances=Tolerances(tol.float64, tol.float32, tol.jacobian), compiler=cfg.compiler, opt=cfg.opt,
        opset=cfg.opset, system=system if system_given else None,
    )  # fmt: skip
