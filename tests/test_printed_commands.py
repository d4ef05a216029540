"""Every printed command pastes and runs, whatever the path: values quoted for Hydra, the line for the shell."""

from __future__ import annotations

import json
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
from hydra.core.override_parser.overrides_parser import OverridesParser

from pinnmpc.training.run import resume_command
from pinnmpc.util.commands import command_line, hydra_quote, override
from tests.conftest import ROOT

NASTY = [  # run dir names a user may well have
    "plain",
    "with space",
    "a,b",
    "key=value",
    "it's",
    'say "hi"',
    "[bracketed]",
    "{braced}",
    "ünïcödé ©",
    "back\\slash",
    "ends in backslash\\",
    "quote\\'mix",
    "1e3",
    "null",
    "true",
    "tab\there",
]


def _value(words: list[str], key: str) -> object:
    """The value Hydra's override parser gives key in a command split as the shell splits it."""
    parser = OverridesParser.create()
    (arg,) = [w for w in words if w.split("=", 1)[0] == key]
    return parser.parse_override(arg).value()


@pytest.mark.parametrize("name", NASTY)
def test_resume_command_round_trips_through_the_shell_and_hydra(tmp_path, name):
    run_dir = tmp_path / name / "run"
    overrides = ["system=planar3", "model.hidden=[64,64]", "trainer.max_time='00:00:10:00'", "resume=false"]
    words = shlex.split(resume_command(overrides, run_dir))
    assert words[:3] == ["python", "-m", "pinnmpc.train"]
    assert _value(words, "hydra.run.dir") == str(run_dir)
    assert words[3:6] == overrides[:3]  # the user's overrides as Hydra got them, resume=false dropped
    assert words.count("resume=true") == 1


@pytest.mark.parametrize("name", NASTY)
def test_quoted_values_parse_back_to_themselves(name):
    for value in (name, f"/tmp/{name}/x", f"{name}'"):
        assert OverridesParser.create().parse_override(f"k={hydra_quote(value)}").value() == value


def test_a_printed_command_runs_from_a_shell_in_a_run_dir_with_every_awkward_character(tmp_path):
    run_dir = tmp_path / "a b,c=d 'q' \"dq\" [x] ü"
    line = command_line([
        sys.executable, "-m", "pinnmpc.closed_loop", "max_steps=2", "progress=false", "plots=false",
        override("hydra.run.dir", str(run_dir)),
    ])  # fmt: skip
    r = subprocess.run(["bash", "-c", line], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    m = json.loads((run_dir / "metrics.json").read_text())
    assert m["status"] == "ok" and m["steps"] == 2
    assert str(run_dir) in r.stdout  # the headline names where the outputs went
    assert Path(run_dir / "closed_loop.log").is_file()
