"""Run a CLI body so that bad input ends in one clear line and a non-zero exit, not a traceback."""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
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


def run_cli(body: Callable[[], T], prog: str) -> T:
    """Call body; a user error or failed run becomes `prog: error: message` on stderr and exit code 2 or 1."""
    try:
        return body()
    except (*USER_ERRORS, *RUN_FAILURES) as e:
        if verbose():
            raise
        message = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        print(f"{prog}: error: {message} (HYDRA_FULL_ERROR=1 for a traceback)", file=sys.stderr)
        sys.exit(EXIT_RUN_FAILED if isinstance(e, RUN_FAILURES) else EXIT_BAD_INPUT)
