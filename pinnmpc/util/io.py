"""Atomic writes: a killed run never leaves a half-written checkpoint, metrics file or trajectory."""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np


def _umask() -> int:
    """The process umask (reading it means setting it, so set it straight back)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write(path: str | Path, write: Callable[[Path], None], suffix: str = ".tmp") -> Path:
    """Write through a temporary file in the same folder, then rename over the target.

    suffix lets writers that sniff the format from the name (e.g. a GIF writer) work;
    the result gets ordinary permissions (mkstemp's are owner-only).
    """
    return _through_temp(path, write, suffix, replace=True)


def atomic_create(path: str | Path, write: Callable[[Path], None], suffix: str = ".tmp") -> Path:
    """As atomic_write, but a file already at path is never replaced: FileExistsError (a hard link is the
    rename that refuses an existing target), so data someone else wrote there survives."""
    return _through_temp(path, write, suffix, replace=False)


def _through_temp(path: str | Path, write: Callable[[Path], None], suffix: str, replace: bool) -> Path:
    """write() into a temporary file beside path, then rename it over path (replace) or hard-link it there."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    os.close(fd)
    try:
        write(Path(tmp))
        os.chmod(tmp, 0o666 & ~_umask())
        if replace:
            os.replace(tmp, path)
        else:
            os.link(tmp, path)
    finally:
        Path(tmp).unlink(missing_ok=True)  # after a rename nothing is left to remove
    return path


def save_json(path: str | Path, data: Any) -> Path:
    """JSON with plain numbers, written atomically."""
    return atomic_write(path, lambda p: p.write_text(json.dumps(data, indent=2, default=_plain) + "\n"))


def save_npz(path: str | Path, **arrays: np.ndarray) -> Path:
    """Compressed npz, written atomically (np.savez would append .npz to the temp name)."""

    def write(p: Path) -> None:
        with open(p, "wb") as f:
            np.savez_compressed(f, **arrays)

    return atomic_write(path, write)


def save_torch(path: str | Path, obj: Any) -> Path:
    """torch.save, written atomically."""
    import torch  # here: the commands' --help and refusals do not wait for torch

    return atomic_write(path, lambda p: torch.save(obj, p))


def plain(data: Any) -> Any:
    """data as JSON types (dicts, lists, numbers, strings): what torch.load(weights_only=True) reads back."""
    return json.loads(json.dumps(data, default=_plain))


def _plain(value: Any) -> Any:
    """numpy/torch scalars and arrays, and OmegaConf containers, as plain JSON values."""
    omegaconf = sys.modules.get("omegaconf")  # likewise a config node
    if omegaconf is not None and isinstance(value, omegaconf.DictConfig | omegaconf.ListConfig):
        return omegaconf.OmegaConf.to_container(value, resolve=True)
    torch = sys.modules.get("torch")  # a tensor can only be here if torch is loaded
    if torch is not None and isinstance(value, torch.Tensor):
        value = value.detach().cpu().numpy()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"cannot write {type(value).__name__} to JSON")


def append_log(path: Path, message: str) -> None:
    """One timestamped line at the end of a run's log file."""
    with path.open("a", encoding="utf-8") as f:
        f.write(f"[{time.strftime('%Y-%m-%d %H:%M:%S')}] {message}\n")
