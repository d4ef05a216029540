"""A reference trajectory as data: validated once on construction, so no consumer re-checks it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


class ReferenceError(ValueError):
    """Bad reference input; the message names the bad value and what was expected."""


@dataclass(frozen=True, eq=False)
class Reference:
    """A sampled state trajectory the controller tracks; validated on construction so no consumer re-checks it."""

    t: np.ndarray
    x: np.ndarray
    name: str

    def __post_init__(self) -> None:
        """Coerce to float64 copies and reject anything a tracking loop would choke on later."""
        t = _as_float(self.t, "t", self.name)
        x = _as_float(self.x, "x", self.name)
        if t.ndim != 1:
            raise ReferenceError(f"{self.name}: t has shape {t.shape}; expected (N,)")
        if x.ndim != 2 or x.shape[0] != len(t) or x.shape[1] < 2 or x.shape[1] % 2:
            hint = " (transposed?)" if x.ndim == 2 and x.shape[1] == len(t) else ""
            hint = hint or (", an odd number of columns" if x.ndim == 2 and x.shape[1] % 2 else "")
            raise ReferenceError(
                f"{self.name}: x has shape {x.shape}{hint}; expected ({len(t)}, nx): positions, then velocities"
            )
        if len(t) < 2:
            raise ReferenceError(f"{self.name}: {len(t)} sample(s); expected at least 2")
        bad_t = np.flatnonzero(~np.isfinite(t))
        if bad_t.size:
            i = int(bad_t[0])
            raise ReferenceError(f"{self.name}: non-finite time {t[i]} at sample {i}; expected finite numbers")
        bad_x = np.argwhere(~np.isfinite(x))
        if bad_x.size:
            i, j = (int(v) for v in bad_x[0])
            raise ReferenceError(
                f"{self.name}: non-finite state {j} = {x[i, j]} at sample {i} (t={t[i]:g}); expected finite numbers"
            )
        bad_dt = np.flatnonzero(np.diff(t) <= 0)
        if bad_dt.size:
            i = int(bad_dt[0]) + 1
            raise ReferenceError(
                f"{self.name}: time not strictly increasing at sample {i}: t[{i - 1}]={t[i - 1]:g}, t[{i}]={t[i]:g}; "
                "expected strictly increasing times"
            )
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "x", x)
        object.__setattr__(self, "name", str(self.name))

    def __len__(self) -> int:
        """Number of samples, so callers can size horizons without reaching into the arrays."""
        return len(self.t)


def _as_float(value: object, what: str, name: str) -> np.ndarray:
    """Copy to float64 so a caller's buffer is never aliased and non-numeric input fails with a clear message."""
    if np.iscomplexobj(value):  # a cast would drop the imaginary parts with only a warning
        raise ReferenceError(f"{name}: {what} is complex; expected real float arrays")
    try:
        return np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ReferenceError(f"{name}: {what} is not numeric ({exc}); expected float arrays") from None
