"""Stopping a long run cleanly: the first SIGTERM/SIGINT asks for a stop at the next safe point."""

from __future__ import annotations

import signal
import sys
import threading
from types import FrameType
from typing import Any


class StopSignal:
    """SIGTERM/SIGINT ask a long run to stop at its next safe point (a closed-loop step, a training epoch, cut
    short); a second one stops at once. Use as a context manager around the run; exit_code is 128 + the signal."""

    SIGNALS = (signal.SIGTERM, signal.SIGINT)

    def __init__(self) -> None:
        self.signum: int | None = None
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> StopSignal:
        self.install()
        return self

    def __exit__(self, *exc: object) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous = {}

    def install(self) -> None:
        """Take over both signals (again, e.g. after Lightning registered its own SIGTERM handler)."""
        if threading.current_thread() is not threading.main_thread():
            return  # signals reach the main thread only
        for signum in self.SIGNALS:
            previous = signal.signal(signum, self._handle)
            self._previous.setdefault(signum, previous)

    def _handle(self, signum: int, _frame: FrameType | None) -> None:
        """First signal: note it; second: stop now."""
        if self.signum is not None:
            raise KeyboardInterrupt
        self.signum = signum
        print(
            f"\nreceived {self.name}: stopping at the next safe point (send it again to stop at once)", file=sys.stderr
        )

    @property
    def requested(self) -> bool:
        """Whether a stop was asked for."""
        return self.signum is not None

    @property
    def name(self) -> str:
        """SIGTERM / SIGINT."""
        return signal.Signals(self.signum).name if self.signum is not None else ""

    @property
    def exit_code(self) -> int:
        """What a shell reports for a process ended by that signal."""
        return 128 + (self.signum or 0)
