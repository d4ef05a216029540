"""Commands printed for a user to paste (a resume command, say): every override value quoted for Hydra's override
grammar, then the whole line for the shell, so that it runs whatever the paths hold (spaces, commas, `=`, quotes,
brackets, non-ASCII)."""

from __future__ import annotations

import re
import shlex
from collections.abc import Sequence

_TRAILING_BACKSLASHES = re.compile(r"(\\+)('|$)")  # backslashes before a quote or the closing quote double up


def _parses_as(override: str) -> object:
    """What Hydra's override parser makes of `override`'s value (None where it does not parse)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    try:
        return OverridesParser.create().parse_override(override).value()
    except (HydraException, ValueError):
        return None


def hydra_quote(value: str) -> str:
    """value as a Hydra override value that parses back to exactly this string: as it is where it already does, else
    in single quotes with quotes (and the backslashes before them) escaped as Hydra's grammar asks."""
    if value and _parses_as(f"k={value}") == value:
        return value
    escaped = _TRAILING_BACKSLASHES.sub(lambda m: m[1] * 2 + m[2], value).replace("'", "\\'")
    return f"'{escaped}'"


def override(key: str, value: str) -> str:
    """One `key=value` override whose value round-trips through Hydra's parser."""
    return f"{key}={hydra_quote(str(value))}"


def command_line(words: Sequence[str]) -> str:
    """The words (program, then overrides as Hydra should see them) as one line a POSIX shell splits back into them."""
    return shlex.join([str(w) for w in words])
