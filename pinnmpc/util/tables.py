"""Markdown helpers shared by every report (bench, robustness, sweep): one table format everywhere."""

from __future__ import annotations

from collections.abc import Sequence


def fmt(value: float | int | str | None, spec: str = ".3g") -> str:
    """Table cell: numbers compact, missing values as a dash."""
    if value is None:
        return "—"
    if isinstance(value, str):
        return value
    if isinstance(value, int):
        return str(value)
    return format(value, spec)


def md_table(headers: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """A GitHub-flavoured markdown table."""
    lines = ["| " + " | ".join(headers) + " |", "|" + "|".join("---" for _ in headers) + "|"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)
