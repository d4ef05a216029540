"""`python -m pinnmpc.curves RUN_DIR[=LABEL] ... --out FILE.png`: validation accuracy against training wall time.

Reads the TensorBoard scalars every training run writes (`<run dir>/tensorboard/`), so runs of different
optimisers, sizes or schedules compare on the one axis a user pays for. Time is the training time each
validation logged (`time/train_s`: set-up and pauses before a resume left out); runs older than that scalar count
from the logger's start, leaving out pauses between a killed run and its resume.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pinnmpc.training.curves import plot_curves, read_curve, write_csv


def main(argv: list[str] | None = None) -> int:
    """CLI: plot the runs named on the command line."""
    parser = argparse.ArgumentParser(prog="python -m pinnmpc.curves", description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="training run dirs, each optionally DIR=LABEL")
    parser.add_argument("--out", type=Path, required=True, help="PNG to write (a CSV of the points goes beside it)")
    parser.add_argument("--title", default="", help="figure title")
    args = parser.parse_args(argv)
    if args.out.suffix.lower() != ".png":
        print(f"pinnmpc.curves: error: --out {args.out}: expected a .png file name", file=sys.stderr)
        return 2
    curves = []
    for spec in args.runs:
        path, _, label = spec.partition("=")
        try:
            curves.append(read_curve(Path(path), label or None))
        except (FileNotFoundError, ValueError) as e:
            print(f"pinnmpc.curves: error: {e}", file=sys.stderr)
            return 2
    labels = [c.label for c in curves]
    twice = sorted({label for label in labels if labels.count(label) > 1})
    if twice:
        print(f"pinnmpc.curves: error: label {twice[0]!r} names two runs; expected one label per run", file=sys.stderr)
        return 2
    plot_curves(curves, args.out, args.title)
    write_csv(curves, args.out.with_suffix(".csv"))
    print(f"wrote {args.out} and {args.out.with_suffix('.csv')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
