"""The small interface the controller depends on: a trained flow map, no Lightning needed."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, ClassVar

import torch
from torch import Tensor

from pinnmpc.surrogate.network import PINN
from pinnmpc.surrogate.numpy_flow import NumpyFlow
from pinnmpc.surrogate.staged import pinn_from_state
from pinnmpc.systems.base import Box
from pinnmpc.util.io import plain, save_torch

FORMAT = "pinnmpc-surrogate"
FORMAT_VERSION = 1
REQUIRED_FACTS = ("tau", "state_names", "input_names", "model")  # what load_surrogate needs besides the weights
CHECKPOINTS = Path(__file__).resolve().parents[1] / "checkpoints"  # shipped networks, one default per system
DEFAULT_SYSTEM = "powercube"  # load_surrogate() without a system
SHIPPED = CHECKPOINTS / f"{DEFAULT_SYSTEM}.pt"


def shipped(system: str | None = None) -> Path:
    """The shipped default network of a system (pinnmpc/checkpoints/<system>.pt)."""
    name = DEFAULT_SYSTEM if system is None else str(system)
    path = CHECKPOINTS / f"{name}.pt"
    if not path.is_file():
        have = sorted(p.stem for p in CHECKPOINTS.glob("*.pt") if "-" not in p.stem)
        raise CheckpointError(
            f"system={name!r} has no shipped checkpoint ({path.name}); shipped: {have}. "
            f"Train one with `make train system={name}` and pass its surrogate.pt"
        )
    return path


class CheckpointError(ValueError):
    """A checkpoint that cannot serve as a surrogate; the message says why and what was expected."""


class Dimensions:
    """nx and nu from the state and input names, for anything with the surrogate interface."""

    state_names: tuple[str, ...]
    input_names: tuple[str, ...]

    @property
    def nx(self) -> int:
        """State dimension."""
        return len(self.state_names)

    @property
    def nu(self) -> int:
        """Input dimension."""
        return len(self.input_names)


class Surrogate(Dimensions):
    """x(t) = flow from x0 under zero-hold u, batched over leading dimensions, float64 by default."""

    array_api: ClassVar[str] = "torch"  # a FlowMap (pinnmpc.surrogate.flowmap) on torch tensors, differentiable

    def __init__(
        self,
        model: PINN,
        tau: float,
        state_names: tuple[str, ...],
        input_names: tuple[str, ...],
        meta: dict[str, Any] | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        self.model = model.to(dtype).eval().requires_grad_(False)
        self.tau = float(tau)
        self.dtype = dtype
        self.state_names, self.input_names = tuple(state_names), tuple(input_names)
        cfg = model.config
        self.state_box = Box(cfg["state_low"], cfg["state_high"])
        self.input_box = Box(cfg["input_low"], cfg["input_high"])
        self.t_max = cfg["t_max"]
        if not 0.0 < self.tau <= self.t_max * (1 + 1e-9):  # x(tau) would be the network's extrapolation in time
            raise CheckpointError(
                f"surrogate tau={self.tau:g} s lies outside the interval (0, t_max={self.t_max:g}] s it was trained "
                "on; expected 0 < tau <= t_max (a hand-edited checkpoint?)"
            )
        self.meta = meta or {}
        low, high = cfg["state_low"], cfg["state_high"]
        turning = {i for i in cfg.get("periodic", ()) if high[i] - low[i] >= 2 * math.pi - 1e-9}
        self.domain = Box(  # where predictions are trained: unbounded in angles whose box is a full turn (exact
            [-math.inf if i in turning else v for i, v in enumerate(low)],  # there by design); a limited joint fed
            [math.inf if i in turning else v for i, v in enumerate(high)],  # as (sin, cos) keeps its limits
        )

    def _check(self, x0: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """Tensors (numpy arrays and lists taken too) in the surrogate's dtype, batch shapes broadcast against each
        other (one input for many states, or the reverse); readable errors otherwise."""
        x0, u = torch.as_tensor(x0, dtype=self.dtype), torch.as_tensor(u, dtype=self.dtype)
        if x0.ndim == 0 or u.ndim == 0 or x0.shape[-1] != self.nx or u.shape[-1] != self.nu:
            raise ValueError(
                f"surrogate expects x0 (..., {self.nx}) {self.state_names} and u (..., {self.nu}) {self.input_names}, "
                f"got x0 {tuple(x0.shape)} and u {tuple(u.shape)}"
            )
        batch = _batch(x0=x0, u=u)
        return x0.expand(*batch, self.nx), u.expand(*batch, self.nu)

    def __call__(self, t: Tensor, x0: Tensor, u: Tensor) -> Tensor:
        """x(t) for t (..., 1), x0 (..., nx), u (..., nu); differentiable w.r.t. x0 and u."""
        x0, u = self._check(x0, u)
        t = torch.as_tensor(t, dtype=self.dtype)
        if t.ndim == 0 or t.shape[-1] != 1:
            raise ValueError(f"surrogate expects t with last dimension 1, got t {tuple(t.shape)}")
        if t.numel() and (float(t.min()) < 0.0 or float(t.max()) > self.t_max * (1 + 1e-9)):
            raise ValueError(
                f"surrogate expects t in [0, t_max={self.t_max:g}] s (the interval it was trained on), got t from "
                f"{float(t.min()):g} to {float(t.max()):g}"
            )
        batch = _batch(t=t, x0=x0, u=u)
        return self.model(t.expand(*batch, 1), x0.expand(*batch, self.nx), u.expand(*batch, self.nu))

    def at(self, tau: float) -> Surrogate:
        """The same network stepping tau s instead (0 < tau <= t_max): a part of a period split in two
        (pinnmpc.surrogate.delayed_command)."""
        return Surrogate(self.model, tau, self.state_names, self.input_names, self.meta, self.dtype)

    def step(self, x0: Tensor, u: Tensor) -> Tensor:
        """x(tau): one zero-hold sampling period."""
        x0, u = self._check(x0, u)
        return self.model(torch.full_like(x0[..., :1], self.tau), x0, u)

    def step_with_jacobian(self, x0: Tensor, u: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """x(tau) with A = dx/dx0 (..., nx, nx) and B = dx/du (..., nx, nu), in one forward-mode pass."""
        x0, u = self._check(x0, u)
        x1, jac = self.model.with_jacobian(torch.full_like(x0[..., :1], self.tau), x0, u)
        return x1, jac[..., : self.nx], jac[..., self.nx :]

    @property
    def approximate_jacobians(self) -> bool:
        """Whether its numpy path's A, B stand in for the derivatives of its step (NumpyFlow.approximate_jacobians:
        a prior whose Jacobian is another's); the torch path's are exact."""
        prior = getattr(self.model, "prior", None)
        return prior is not None and prior.stand_in_jacobian

    def numpy_flow(self) -> NumpyFlow:
        """The same x(tau) as plain numpy (weights copied, t = tau folded in): the controller's batch-1 fast path."""
        return NumpyFlow.from_pinn(self.model, self.tau, self.state_names, self.input_names)

    def save(self, path: str | Path) -> Path:
        """Lean checkpoint (weights and the facts needed to rebuild), written atomically."""
        return save_torch(
            path,
            {
                "format": FORMAT,
                "version": FORMAT_VERSION,
                "tau": self.tau,
                "state_names": list(self.state_names),
                "input_names": list(self.input_names),
                "model": self.model.config,
                "state_dict": self.model.state_dict(),
                "meta": plain(self.meta),  # a config node in it would make the file unreadable with weights_only
            },
        )


def _read(path: Path) -> dict[str, Any]:
    """torch.load with errors a user can act on."""
    if not path.exists():
        raise CheckpointError(
            f"checkpoint not found: {path} (train one with `make train`, or pass path=None for the shipped one)"
        )
    if path.is_dir():
        raise CheckpointError(f"checkpoint path is a folder: {path}; expected a .pt or .ckpt file")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)  # never runs code from a file
    except Exception as e:  # any failure to unpickle means the file is not a usable checkpoint
        raise CheckpointError(
            f"checkpoint {path} cannot be read ({type(e).__name__}: corrupt, truncated or not a torch file); "
            "expected a .pt or .ckpt written by pinnmpc"
        ) from e
    if not isinstance(obj, dict):
        raise CheckpointError(f"checkpoint {path} holds a {type(obj).__name__}; expected a pinnmpc checkpoint dict")
    return obj


def _unpack(obj: dict[str, Any], path: Path) -> tuple[dict[str, Any], dict[str, Tensor], dict[str, Any]]:
    """Model config, weights and facts from either a lean file or a Lightning checkpoint."""
    if obj.get("format") == FORMAT:
        facts = obj
        state = obj.get("state_dict")
    elif "pinnmpc" in obj and "state_dict" in obj:
        facts = obj["pinnmpc"]
        state = {k.removeprefix("model."): v for k, v in obj["state_dict"].items() if k.startswith("model.")}
    else:
        raise CheckpointError(f"{path} is not a pinnmpc checkpoint; expected a surrogate .pt or a training .ckpt")
    missing = [k for k in REQUIRED_FACTS if k not in facts] + ([] if isinstance(state, dict) else ["state_dict"])
    if missing:
        raise CheckpointError(f"{path} lacks {missing}; expected a complete pinnmpc checkpoint")
    if facts.get("version", FORMAT_VERSION) > FORMAT_VERSION:
        raise CheckpointError(
            f"{path} has format version {facts['version']}; this pinnmpc reads up to {FORMAT_VERSION}"
        )
    return facts["model"], state, facts


def _batch(**arrays: Tensor) -> torch.Size:
    """The batch shape arrays (..., n) share (broadcast), or an error naming each one's shape."""
    try:
        return torch.broadcast_shapes(*(a.shape[:-1] for a in arrays.values()))
    except RuntimeError:
        names, shapes = " and ".join(arrays), " and ".join(f"{k} {tuple(a.shape)}" for k, a in arrays.items())
        raise ValueError(
            f"surrogate expects {names} with the same (or broadcastable) batch shapes, got {shapes}"
        ) from None


def load_surrogate(
    path: str | Path | None = None,
    system: str | None = None,
    nx: int | None = None,
    nu: int | None = None,
    dtype: torch.dtype = torch.float64,
    state_names: tuple[str, ...] | None = None,
) -> Surrogate:
    """Load a trained surrogate: a file, or (path=None) the one shipped for `system` (None: the PowerCube).

    nx/nu, the system's state_names, or `system` with a path, guard against a network trained for another robot."""
    if system is not None and not isinstance(system, str):
        raise TypeError(f"system must be a system name like 'planar3', got {type(system).__name__}")
    asked = dtype
    if isinstance(dtype, str):  # "float64" as well as torch.float64
        dtype = getattr(torch, dtype, None)
    if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
        raise TypeError(f"dtype must be a torch floating dtype (e.g. torch.float64 or 'float64'), got {asked!r}")
    if path is not None and system is not None and state_names is None:
        from pinnmpc.systems.registry import load_system

        state_names = tuple(load_system(system).state_names)
    path = shipped(system) if path is None else Path(path)
    obj = _read(path)
    config, state, facts = _unpack(obj, path)
    names, input_names = tuple(facts["state_names"]), tuple(facts["input_names"])
    if state_names is not None and tuple(state_names) != names:
        raise CheckpointError(
            f"{path} was trained for states {list(names)}; this system has {list(state_names)} "
            f"(pass the checkpoint of this system, or system=<its name>)"
        )
    state_names = names
    for what, want, have in (("state", nx, len(state_names)), ("input", nu, len(input_names))):
        if want is not None and want != have:
            raise CheckpointError(f"{path} was trained for a system with {what} dimension {have}; expected {want}")
    try:
        model = pinn_from_state(config, state)
    except FileNotFoundError as e:  # its prior's arm: the URDF the network was trained on has moved
        raise CheckpointError(f"{path}: its prior's arm is gone ({e})") from None
    except (RuntimeError, TypeError, ValueError) as e:
        raise CheckpointError(f"{path}: weights do not fit the stored network config ({e})") from e
    return Surrogate(model, facts["tau"], state_names, input_names, meta=facts.get("meta", {}), dtype=dtype)
