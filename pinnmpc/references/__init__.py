"""Reference trajectories: the paper's MATLAB files, user files (.npz, .csv) and the built-in paths."""

from pinnmpc.references.builtin import BUILTIN_DT, builtin_reference
from pinnmpc.references.data import Reference, ReferenceError
from pinnmpc.references.files import load_reference, read_reference, resample

__all__ = [
    "BUILTIN_DT",
    "Reference",
    "ReferenceError",
    "builtin_reference",
    "load_reference",
    "read_reference",
    "resample",
]
