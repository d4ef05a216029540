"""Where the package and its Hydra config tree lie: the folders a job reads and never writes."""

from __future__ import annotations

from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1]  # the installed package
CONF = PACKAGE.parent / "conf"  # the Hydra config tree the entry points compose from
