"""Checks of single settings: each returns None for an allowed value, else a phrase saying what is allowed."""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf

Dims = Mapping[str, int]  # {"nx": ..., "nu": ...} of the system the run is for
Check = Callable[[Any, Dims], str | None]  # None when the value is allowed, else what is allowed
_ABSENT = object()  # a key a Python caller's config leaves out: nothing to check


class SettingError(ValueError):
    """Bad setting; the message names the key, the value and what is allowed."""


def _is_int(v: Any) -> bool:
    """Integers only: bool is an int to Python but never a count, 2.5 must not silently become 2."""
    return isinstance(v, int) and not isinstance(v, bool)


def _is_real(v: Any) -> bool:
    """Finite numbers only: NaN and inf pass every comparison-free check downstream and fail much later."""
    return (_is_int(v) or isinstance(v, float)) and math.isfinite(v)


def _num(v: float) -> str:
    """4294967295 stays an integer in messages, 0.1 stays short."""
    return str(v) if _is_int(v) else f"{v:g}"


def _range(lo: float | None, hi: float | None, lo_open: bool) -> str:
    """'>= 0', '> 0', 'in [0, 1]' for the messages."""
    if lo is not None and hi is not None:
        return f" in {'(' if lo_open else '['}{_num(lo)}, {_num(hi)}]"
    if lo is not None:
        return f" {'>' if lo_open else '>='} {_num(lo)}"
    return f" <= {_num(hi)}" if hi is not None else ""


def _inside(v: float, lo: float | None, hi: float | None, lo_open: bool) -> bool:
    """Range test matching _range."""
    return (lo is None or (v > lo if lo_open else v >= lo)) and (hi is None or v <= hi)


def integer(lo: int | None = None, hi: int | None = None) -> Check:
    """An int in [lo, hi]."""
    allowed = "an integer" + _range(lo, hi, False)
    return lambda v, _d: None if _is_int(v) and _inside(v, lo, hi, False) else allowed


def whole(lo: int) -> Check:
    """A whole number >= lo: a count a settings dataclass holds (iterations, sub-steps)."""
    return lambda v, _d: None if _is_int(v) and v >= lo else f"a whole number >= {lo}"


def real(lo: float | None = None, hi: float | None = None, lo_open: bool = False) -> Check:
    """A finite number in the range (lo excluded with lo_open)."""
    allowed = "a finite number" + _range(lo, hi, lo_open)
    return lambda v, _d: None if _is_real(v) and _inside(v, lo, hi, lo_open) else allowed


def positive() -> Check:
    """A finite number > 0."""
    return real(0.0, lo_open=True)


def boolean() -> Check:
    """true or false."""
    return lambda v, _d: None if isinstance(v, bool) else "true or false"


def text() -> Check:
    """A non-empty string (paths, names)."""
    return lambda v, _d: None if isinstance(v, str) and v.strip() else "a non-empty string"


def one_of(*choices: str) -> Check:
    """One of a few names."""
    return lambda v, _d: None if v in choices else "one of " + ", ".join(choices)


def optional(check: Check) -> Check:
    """null, or what check allows."""

    def _check(v: Any, dims: Dims) -> str | None:
        bad = None if v is None else check(v, dims)
        if bad is None:
            return None
        # "or null" after a list would read as allowed for each entry
        return f"null or {bad}" if bad.startswith("a list") else f"{bad} or null"

    return _check


_NOTHING = object()  # a value no check allows: asked with it, a check describes what it allows


def _length(n: int | str, dims: Dims) -> int:
    """A fixed length or the system's nx/nu."""
    return dims[n] if isinstance(n, str) else n


def vector(n: int | str, element: Check | None = None) -> Check:
    """A list of n entries (n: a number or 'nx'/'nu'), each finite (or what element allows)."""
    element = element or real()

    def _check(v: Any, dims: Dims) -> str | None:
        size = _length(n, dims)
        desc = element(_NOTHING, dims) or ""
        ok = isinstance(v, list) and len(v) == size and all(element(e, dims) is None for e in v)
        return None if ok else f"a list of {size} entries ({n}), each {desc}"

    return _check


def listof(element: Check, empty: bool = False) -> Check:
    """A list (non-empty unless `empty`), each entry allowed by element (grids, layer widths)."""

    def _check(v: Any, dims: Dims) -> str | None:
        ok = isinstance(v, list) and (empty or len(v) > 0) and all(element(e, dims) is None for e in v)
        return None if ok else f"a {'' if empty else 'non-empty '}list, each entry {element(_NOTHING, dims)}"

    return _check


def by_horizon() -> Check:
    """A limit per prediction horizon: a mapping of whole numbers >= 1 (or their digits as text) to numbers > 0."""

    def _check(v: Any, _d: Dims) -> str | None:
        keys_ok = isinstance(v, dict) and all(
            (_is_int(h) and h >= 1) or (isinstance(h, str) and h.isdigit() and int(h) >= 1) for h in v
        )
        ok = keys_ok and all(_is_real(x) and x > 0 for x in v.values())
        return None if ok else "a mapping of horizons (whole numbers >= 1) to limits > 0, e.g. {5: 2.0, 20: 2.5}"

    return _check


def weight(n: str) -> Check:
    """A cost weight: n non-negative finite numbers (a diagonal) or an n x n symmetric PSD matrix."""

    def _check(v: Any, dims: Dims) -> str | None:
        size = _length(n, dims)
        allowed = f"{size} finite numbers >= 0 (the diagonal) or a {size} x {size} symmetric PSD matrix ({n})"
        if not isinstance(v, list) or len(v) != size:
            return allowed
        if all(_is_real(e) for e in v):
            return None if all(e >= 0 for e in v) else allowed
        if not all(isinstance(row, list) and len(row) == size and all(_is_real(e) for e in row) for row in v):
            return allowed
        m = np.array(v, dtype=np.float64)
        scale = max(1.0, float(np.abs(m).max()))
        psd = np.allclose(m, m.T, atol=1e-12 * scale) and np.linalg.eigvalsh(m).min() >= -1e-12 * scale
        return None if psd else allowed

    return _check


def joint_index() -> Check:
    """A joint number 0..nq-1 (nq = nx / 2)."""

    def _check(v: Any, dims: Dims) -> str | None:
        nq = dims["nx"] // 2
        return None if _is_int(v) and 0 <= v < nq else f"a joint number 0..{nq - 1}"

    return _check


def per_state_targets() -> Check:
    """null (no targets), or one target per state, each a number >= 0 or null (none for that state)."""
    inner = vector("nx", optional(real(0.0)))

    def _check(v: Any, dims: Dims) -> str | None:
        bad = None if v is None else inner(v, dims)
        return None if bad is None else f"null or {bad}"

    return _check


def duration() -> Check:
    """Lightning's wall-time budget DD:HH:MM:SS, above zero (a zero budget trains nothing and writes no network)."""
    pattern = re.compile(r"\d+:\d\d:\d\d:\d\d")

    def _check(v: Any, _d: Dims) -> str | None:
        ok = isinstance(v, str) and pattern.fullmatch(v.strip()) and any(int(f) for f in v.strip().split(":"))
        return None if ok else "a duration DD:HH:MM:SS above zero"

    return _check


def epochs() -> Check:
    """Lightning's max_epochs: -1 (no limit) or at least one epoch (0 trains nothing and writes no network)."""
    return lambda v, _d: None if _is_int(v) and (v == -1 or v >= 1) else "-1 (no limit) or an integer >= 1"


def check_settings(section: str, settings: Any, checks: Mapping[str, Check]) -> None:
    """A settings dataclass's fields by their checks (its __post_init__); the first bad one raises one line naming
    `section.key`, its value and what is allowed."""
    for key, check in checks.items():
        value = getattr(settings, key)
        allowed = check(value, {})
        if allowed is not None:
            raise ValueError(f"{section}.{key}={value!r}: expected {allowed}")


SEED = integer(0, 2**32 - 1)  # what numpy and Lightning accept


def setting(
    default: Any = dataclasses.MISSING, *, check: Check | None = None, factory: Any = dataclasses.MISSING
) -> Any:
    """A settings dataclass field with its check declared beside it (check_fields runs them): no parallel table."""
    return dataclasses.field(default=default, default_factory=factory, metadata={"check": check})


def check_fields(section: str, settings: Any, dims: Dims) -> None:
    """Every field of a settings dataclass by the check declared with it, nested settings under their own key; the
    first bad one raises one line naming `section.key`, its value and what is allowed."""
    for f in dataclasses.fields(settings):
        value = getattr(settings, f.name)
        if dataclasses.is_dataclass(value):
            check_fields(f"{section}.{f.name}", value, dims)
        check = f.metadata.get("check")
        allowed = None if check is None else check(plain(value), dims)
        if allowed is not None:
            raise SettingError(f"{section}.{f.name}={plain(value)!r}: expected {allowed}")


def settings_from(cls: type, values: Any, section: str) -> Any:
    """The settings dataclass cls from a config node or dict (nested dataclass fields from nested mappings): an
    unknown or missing key is one line naming it and the keys there are (the checks are check_fields')."""
    if dataclasses.is_dataclass(values):
        return values
    values = dict(plain(values) or {})
    known = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - set(known))
    if unknown:
        raise SettingError(f"{section}.{unknown[0]}: not a setting here; expected one of {sorted(known)}")
    missing = [n for n, f in known.items() if n not in values and _required(f)]
    if missing:
        raise SettingError(f"{section}.{missing[0]} is missing: expected it set (the settings {sorted(known)})")
    for name, value in values.items():
        nested = _nested_default(known[name])
        if nested is not None and isinstance(value, Mapping):  # over the field's own default: a kind's defaults stay
            given = settings_from(type(nested), {**dataclasses.asdict(nested), **value}, f"{section}.{name}")
            values[name] = given
    return cls(**values)


def _required(f: dataclasses.Field) -> bool:
    """A field without a default."""
    return f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING


def _nested_default(f: dataclasses.Field) -> Any:
    """A field's default where it is a settings dataclass (nested settings), else None."""
    if f.default_factory is not dataclasses.MISSING:
        made = f.default_factory()
        return made if dataclasses.is_dataclass(made) else None
    return None


def plain(value: Any) -> Any:
    """Config nodes as plain lists/dicts, for the checks and the messages."""
    if OmegaConf.is_config(value):
        return OmegaConf.to_container(value, resolve=True)
    return value


def validate(cfg: DictConfig, table: Mapping[str, Check], dims: Dims) -> None:
    """Check every key of table that cfg has; the first bad one raises SettingError naming key, value, allowed."""
    for key, check in table.items():
        value = plain(OmegaConf.select(cfg, key, default=_ABSENT))
        if value is _ABSENT:
            continue
        allowed = check(value, dims)
        if allowed is not None:
            raise SettingError(f"{key}={value!r}: expected {allowed}")


def pair(cfg: DictConfig, low_key: str, high_key: str) -> None:
    """low <= high entry by entry, when both are given."""
    low, high = (plain(OmegaConf.select(cfg, k, default=None)) for k in (low_key, high_key))
    if low is not None and high is not None and any(lo > hi for lo, hi in zip(low, high)):
        raise SettingError(f"{low_key}={low} exceeds {high_key}={high}: expected low <= high in every entry")
