"""Run a CLI body so that bad input ends in one clear line and a non-zero exit, not a traceback."""

from __future__ import annotations

import os
import shutil
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

from omegaconf.errors import OmegaConfBaseException

T = TypeVar("T")

USER_ERRORS = (ValueError, FileNotFoundError, KeyError, OmegaConfBaseException)  # bad input, not a bug of ours
RUN_FAILURES = (FloatingPointError,)  # a run that started and went wrong (e.g. a NaN training loss)
EXIT_BAD_INPUT = 2  # exit code for bad input
EXIT_RUN_FAILED = 1  # exit code for a run that started and failed


def verbose() -> bool:
    """Tracebacks on request, as Hydra users expect."""
    return os.environ.get("HYDRA_FULL_ERROR") == "1" or os.environ.get("PINNMPC_VERBOSE") == "1"


def discard_bookkeeping_only(run_dir: Path | None) -> None:
    """Remove a run dir holding nothing but Hydra's .hydra/ and logs: bad input leaves no half-written run."""
    if run_dir is None or not run_dir.is_dir():
        return
    if all(e.name == ".hydra" or (e.is_file() and e.suffix == ".log") for e in run_dir.iterdir()):
        shutil.rmtree(run_dir, ignore_errors=True)


def run_cli(body: Callable[[], T], prog: str, run_dir: Path | None = None) -> T:
    """Call body; a user error or failed run becomes `prog: error: message` on stderr and exit code 2 or 1;
    after bad input, a run_dir that Hydra filled with its bookkeeping only is removed."""
    try:
        return body()
    except (*USER_ERRORS, *RUN_FAILURES) as e:
        if isinstance(e, USER_ERRORS):
            discard_bookkeeping_only(run_dir)
        if verbose():
            raise
        message = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        print(f"{prog}: error: {message} (HYDRA_FULL_ERROR=1 for a traceback)", file=sys.stderr)
        sys.exit(EXIT_RUN_FAILED if isinstance(e, RUN_FAILURES) else EXIT_BAD_INPUT)
