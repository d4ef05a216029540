"""Per-command --help (conf/hydra/help/): each entry point explains the keys a user sets, and only real keys."""

from __future__ import annotations

import re
import subprocess
import sys
from collections.abc import Callable
from functools import cache

import pytest
from omegaconf import DictConfig, OmegaConf

from tests.conftest import CONF, ROOT

COMMANDS = {  # module: its primary config
    "train": "train",
    "closed_loop": "closed_loop",
    "self_loop": "self_loop",
    "residuals": "residuals",
    "time_basis": "time_basis",
    "capacity": "capacity",
    "robustness": "robustness",
    "bench": "bench",
    "collect": "collect",
    "identify": "identify",
    "export": "export",
}
KEY = re.compile(r"^ {2,}([A-Za-z_][\w.]*)=", re.MULTILINE)  # a key at the start of an indented help line
ABSENT = object()


@cache
def _help(module: str) -> str:
    """What `python -m pinnmpc.<module> --help` prints, as a user runs it (once: each start imports torch)."""
    r = subprocess.run(
        [sys.executable, "-m", f"pinnmpc.{module}", "--help"], capture_output=True, text=True, cwd=ROOT, timeout=120
    )
    assert r.returncode == 0, r.stderr[-2000:]
    return r.stdout


def test_closed_loop_help_names_its_keys_and_not_the_training_groups() -> None:
    text = _help("closed_loop")
    assert text.startswith("pinnmpc.closed_loop: ")
    for key in ("system=", "controller=", "controller.solver=", "checkpoint=", "reference.path=", "hydra.run.dir="):
        assert key in text, key
    for key in ("animate=true", "max_steps=", "noise_sigma="):
        assert key in text, key
    assert "Examples:" in text and text.count("python -m pinnmpc.closed_loop") >= 4
    # Hydra's generic page lists every config group of conf/, the training ones too, and dumps the config
    for generic in ("Configuration groups", "hparams_search", "trainer", "module", "collocation", "_target_"):
        assert generic not in text, generic


@pytest.mark.parametrize("module", sorted(COMMANDS))
def test_every_key_a_help_names_exists(module: str, make_cfg: Callable[..., DictConfig]) -> None:
    text = _help(module)
    assert text.startswith(f"pinnmpc.{module}: ") and "Examples:" in text
    assert "Configuration groups" not in text
    cfg = make_cfg(COMMANDS[module])
    keys = set(KEY.findall(text))
    assert len(keys) >= 5, keys
    for key in keys - {"hydra.run.dir"}:
        group = (CONF / key).is_dir()  # e.g. system=, experiment= (a group whose default is null)
        assert group or OmegaConf.select(cfg, key, default=ABSENT) is not ABSENT, f"{module} --help names {key}="


@pytest.mark.parametrize("module", sorted(COMMANDS))
def test_an_unknown_config_option_is_named_in_one_line_before_hydra_starts(module: str) -> None:
    r = subprocess.run(
        [sys.executable, "-m", f"pinnmpc.{module}", "system=nope", "hydra.run.dir=/nonexistent/never"],
        capture_output=True, text=True, cwd=ROOT, timeout=120,
    )  # fmt: skip
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.strip().splitlines() == [
        f"pinnmpc.{module}: error: system='nope': no system/nope.yaml in conf; expected one of "
        "['fr3', 'panda', 'planar3', 'powercube']"
    ]


@pytest.mark.parametrize(
    "arg, line",
    [
        ("controller.solvers.gauss_newton.max_iter=abc", "controller.solvers.gauss_newton.max_iter='abc': expected "
         "a whole number >= 0"),
        ("controller.solvers.gauss_newton.maxiter=3", "unknown setting 'controller.solvers.gauss_newton.maxiter'; "
         "expected one of ['max_iter', 'tol_grad', 'tol_cost', 'tol_gap', 'damping', 'step_lengths', "
         "'reuse_jacobian'] (the fields of gauss_newton)"),
        ("controller.solvers.lifted_gauss_newton.rti_steps=0", "controller.solvers.lifted_gauss_newton.rti_steps=0: "
         "expected a whole number >= 1"),
        ("controller.solvers.rmsprop.lr=2,-1", "controller.solvers.rmsprop.lr=-1: expected a finite number >= 0"),
        ("controller.solvers.newton.tol=1", "controller.solvers.newton.tol: no solver 'newton'; expected one of "
         "['gauss_newton', 'lbfgs', 'lifted_gauss_newton', 'rmsprop']"),
    ],
)  # fmt: skip
def test_a_bad_solver_setting_is_one_line_before_hydra_starts(capsys, arg: str, line: str) -> None:
    from pinnmpc.cli import check_choices

    with pytest.raises(SystemExit) as stop:  # what every command runs before Hydra composes
        check_choices("pinnmpc.closed_loop", [arg, "max_steps=2"])
    assert stop.value.code == 2
    assert capsys.readouterr().err.strip().splitlines() == [f"pinnmpc.closed_loop: error: {line}"]
    if "," not in arg:
        return
    r = subprocess.run(  # a sweep with one bad value, through the real command line: refused before any job runs
        [sys.executable, "-m", "pinnmpc.closed_loop", "-m", arg, "hydra.sweep.dir=/nonexistent/never"],
        capture_output=True, text=True, cwd=ROOT, timeout=120,
    )  # fmt: skip
    assert r.returncode == 2 and r.stderr.strip().splitlines() == [f"pinnmpc.closed_loop: error: {line}"]


def test_only_plain_group_choices_are_checked() -> None:
    from pinnmpc.cli import check_choices

    check_choices("x", ["system=planar3", "controller.horizon=7", "system.tau=0.1", "seed=3", "system=a,b"])
    with pytest.raises(SystemExit) as stop:
        check_choices("x", ["controller=fast"])
    assert stop.value.code == 2


def test_config_dirs_of_the_command_line_count(tmp_path, capsys) -> None:
    from pinnmpc.cli import check_choices

    (tmp_path / "system").mkdir()
    (tmp_path / "system" / "mine.yaml").write_text("{}\n")
    for extra in (["--config-dir", str(tmp_path)], [f"-cd={tmp_path}"], [f"hydra.searchpath=[file://{tmp_path}]"]):
        check_choices("x", [*extra, "system=mine"])  # a user's own arm, outside the package
        with pytest.raises(SystemExit):
            check_choices("x", [*extra, "system=nope"])
        expected = "in any config dir; expected one of ['fr3', 'mine', 'panda', 'planar3', 'powercube']"
        assert expected in capsys.readouterr().err
    check_choices("x", ["hydra.searchpath=[pkg://elsewhere.conf]", "system=nope"])  # Hydra may find it there


def test_a_resume_command_keeps_the_config_dir(tmp_path, monkeypatch) -> None:
    from pinnmpc.cli import config_dir_args

    monkeypatch.chdir(tmp_path)
    args = ["-cd", "arms", "system=mine", "hydra.searchpath=[file:///x]", "seed=1"]
    assert config_dir_args(args) == ["--config-dir", str(tmp_path / "arms"), "hydra.searchpath=[file:///x]"]


@pytest.mark.parametrize("module", sorted(COMMANDS))
def test_a_misspelt_setting_is_named_in_one_line(module: str, capsys) -> None:
    from pinnmpc.cli import check_choices

    with pytest.raises(SystemExit) as stop:
        check_choices(f"pinnmpc.{module}", ["controler=casadi"])
    assert stop.value.code == 2
    assert f"pinnmpc.{module}: error: unknown setting 'controler' (controler=casadi); expected one of [" in (
        capsys.readouterr().err
    )
    check_choices(f"pinnmpc.{module}", ["threads=1", "hydra.run.dir=x", "+new_key=1", "system.tau=0.1"])  # all fine


@pytest.mark.parametrize("module", sorted(COMMANDS))
def test_the_help_page_is_the_template_hydra_composes(module: str) -> None:
    """check_choices prints the template Hydra's own config for the command holds (its `override hydra/help`),
    resolved as Hydra resolves it, so the page is the same without the seconds Hydra spends listing config groups."""
    from hydra import compose, initialize_config_dir

    from pinnmpc.cli.args import help_text

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(config_name=COMMANDS[module], return_hydra_config=True)
    assert help_text(f"pinnmpc.{module}") == cfg.hydra.help.template
    assert _help(module) == cfg.hydra.help.template + "\n"


def test_the_help_page_answers_before_torch_loads() -> None:
    """--help and a refused group option are instant: no command imports torch before its checks pass."""
    for args in (["--help"], ["system=nope"]):
        timed = subprocess.run(
            [sys.executable, "-X", "importtime", "-m", "pinnmpc.closed_loop", *args],
            capture_output=True, text=True, cwd=ROOT, timeout=120,
        )  # fmt: skip
        assert timed.returncode == (0 if args == ["--help"] else 2)
        loaded = {line.rsplit("|", 1)[-1].strip() for line in timed.stderr.splitlines() if "|" in line}
        assert "torch" not in loaded and "lightning" not in loaded, args


@pytest.mark.parametrize("module", sorted(COMMANDS))
def test_an_override_hydra_cannot_parse_is_one_line_and_exit_2(module: str) -> None:
    r = subprocess.run(
        [sys.executable, "-m", f"pinnmpc.{module}", "seed=1", "reference.name=it's", "hydra.run.dir=/nonexistent/n"],
        capture_output=True, text=True, cwd=ROOT, timeout=120,
    )  # fmt: skip
    assert r.returncode == 2 and r.stdout == "", r.stderr[-2000:]
    assert r.stderr.strip().splitlines() == [
        f'pinnmpc.{module}: error: cannot parse the override "reference.name=it\'s" (unexpected "\'" at character '
        "18); expected Hydra's override grammar: quote a value with quotes, brackets, commas or '=', e.g. "
        "reference.name='it\\'s' (docs/troubleshooting.md)"
    ]


@pytest.mark.parametrize(
    "args, said",
    [
        (["x0=[0.1,0"], "'x0=[0.1,0' (no viable alternative at input '[0.1,0'); expected a list as [a,b,...]"),
        (["-m", "--config-dir", ".", "seed=0,1", "a=b=c"], "'a=b=c' (mismatched input '=' expecting <EOF>)"),
        (["--cfg", "job", "-p", "seed", "key"], "'key' (missing EQUAL at '<EOF>'); expected key=value"),
        (['reference.name="x'], "(unexpected '\"' at character 16)"),
    ],
)
def test_every_grammar_error_is_named_before_hydra_starts(capsys, args: list[str], said: str) -> None:
    from pinnmpc.cli import check_choices
    from pinnmpc.cli.args import grammar_error
    from pinnmpc.util.commands import hydra_quote

    with pytest.raises(SystemExit) as stop:
        check_choices("pinnmpc.closed_loop", args)
    assert stop.value.code == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith("pinnmpc.closed_loop: error: cannot parse the override ") and said in line, line
    # what the hint suggests parses, to the very text that was meant
    key, _, value = args[-1].partition("=")
    assert value.startswith("[") or grammar_error(f"{key}={hydra_quote(value)}") is None


def test_overrides_hydra_parses_pass_the_grammar_check() -> None:
    from pinnmpc.cli import check_choices

    fine = ["seed=0,1", "x0=[0.1, 0, 0, 0]", "reference.name='it\\'s'", "hydra.run.dir=/tmp/a b", "x0=null", "~faults"]
    check_choices("pinnmpc.closed_loop", ["-m", *fine, "+extra=${oc.env:HOME}", "--config-dir", str(CONF)])
    check_choices("pinnmpc.closed_loop", ["--version"])  # Hydra answers that itself
