"""The training's structured configs (module, data): the composed config is the dataclasses' defaults, the classes
take their defaults from them, and a bad `module.*` or `data.*` override is one line before Hydra composes."""

from __future__ import annotations

import ast
import dataclasses
import inspect
import subprocess
import sys

import pytest
from omegaconf import OmegaConf

from pinnmpc.cli import check_choices
from pinnmpc.systems import PowerCube
from pinnmpc.training import settings as training_settings
from pinnmpc.training.data import CollocationDataModule
from pinnmpc.training.job_settings import validate_train
from pinnmpc.training.models import build_model
from pinnmpc.training.module import DTYPES, PINNModule
from pinnmpc.training.settings import DataSettings, ModuleSettings
from pinnmpc.training.ssbfgs import HESSIAN_DTYPES, VARIANTS
from pinnmpc.util.checks import SettingError
from tests.conftest import CONF, ROOT, TINY_TRAIN

MODULE_FIELDS = [f.name for f in dataclasses.fields(ModuleSettings)]
SECTIONS = {"module": (ModuleSettings, PINNModule), "data": (DataSettings, CollocationDataModule)}


@pytest.mark.parametrize("section", sorted(SECTIONS))
def test_the_composed_config_is_the_dataclass_defaults(make_cfg, section) -> None:
    settings, _ = SECTIONS[section]
    assert OmegaConf.to_container(make_cfg("train")[section]) == dataclasses.asdict(settings())
    option = {"module": "pinn", "data": "collocation"}[section]
    assert set(OmegaConf.load(CONF / section / f"{option}.yaml")) == {"defaults"}  # every value in one place


@pytest.mark.parametrize("section", sorted(SECTIONS))
def test_the_class_defaults_are_the_dataclass_defaults(section) -> None:
    settings, cls = SECTIONS[section]
    defaults = dataclasses.asdict(settings())
    del defaults["_target_"]
    params = inspect.signature(cls.__init__).parameters
    own = {"self", "system", "model", "tau", "t_max", "seed", "physics", "robot_start"}  # what the run passes
    assert set(params) - own == set(defaults)
    for name, value in defaults.items():
        got = params[name].default
        assert (list(got) if isinstance(value, list) else got) == value, name
    assert defaults["optimizer" if section == "module" else "n_anchor"]  # the project's, not the paper's


def test_a_default_pinn_module_has_the_settings_of_module_pinn(make_cfg) -> None:
    system = PowerCube()
    module = PINNModule(system, build_model(make_cfg("train", TINY_TRAIN), system), tau=0.2)
    want = dataclasses.asdict(ModuleSettings())
    del want["_target_"]
    assert {k: module.hparams[k] for k in want} == want


def test_every_field_is_documented_and_the_names_match_the_classes() -> None:
    tree = ast.parse(inspect.getsource(training_settings))
    for cls in (c for c in tree.body if isinstance(c, ast.ClassDef)):
        body = cls.body
        for i, node in enumerate(body):
            if isinstance(node, ast.AnnAssign):
                after = body[i + 1] if i + 1 < len(body) else None
                documented = isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant)
                assert documented, f"{cls.name}.{node.target.id} has no docstring"
    assert training_settings.SSBFGS_VARIANTS == VARIANTS
    assert set(training_settings.HESSIAN_DTYPES) == set(HESSIAN_DTYPES)
    assert set(training_settings.DTYPES) == set(DTYPES)


def _cli(*args: str) -> subprocess.CompletedProcess:
    """The real command line, as a user runs it."""
    return subprocess.run(
        [sys.executable, "-m", "pinnmpc.train", *args], capture_output=True, text=True, cwd=ROOT, timeout=120
    )


@pytest.mark.parametrize(
    ("arg", "sweep", "line"),
    [
        ("module.lbfgs_max_iter=0", "module.lbfgs_max_iter=5,0", "module.lbfgs_max_iter=0: expected an integer >= 1"),
        ("data.n_collocation=abc", "data.n_collocation=256,abc", "data.n_collocation='abc': expected an integer >= 1"),
        (
            "module.optimizr=x",
            "module.optimizr=x,y",
            f"unknown setting 'module.optimizr' of module=pinn; expected one of {MODULE_FIELDS}",
        ),
    ],
)
def test_a_bad_training_setting_is_one_line_before_hydra_starts(tmp_path, capsys, arg, sweep, line) -> None:
    from pinnmpc.cli import check_choices

    for args in ([arg], ["-m", sweep]):  # what every command runs before Hydra composes; a sweep: before any job
        with pytest.raises(SystemExit) as stop:
            check_choices("pinnmpc.train", args)
        assert stop.value.code == 2
        assert capsys.readouterr().err.strip().splitlines() == [f"pinnmpc.train: error: {line}"]
    if arg.startswith("module.lbfgs"):  # once through the real command line, a sweep
        r = _cli("-m", sweep, f"hydra.sweep.dir={tmp_path / 'sweep'}")
        assert r.returncode == 2 and r.stderr.strip().splitlines() == [f"pinnmpc.train: error: {line}"]
        assert not list(tmp_path.iterdir())


@pytest.mark.parametrize(
    ("arg", "line"),
    [
        ("module.dtype=float16", "module.dtype='float16': expected one of float32, float64"),
        ("module.residual_scale=[1,-1]", "module.residual_scale=[1, -1]: expected auto or a non-empty list"),
        ("module.kinematic_weight=0", "module.kinematic_weight=0: expected a finite number > 0"),
        ("module.robust_delta=-1", "module.robust_delta=-1: expected a finite number > 0 or null"),
        ("module.stall_redraw=maybe", "module.stall_redraw='maybe': expected true or false"),
        ("module.ssbfgs_variant=sr1", "module.ssbfgs_variant='sr1': expected one of ssbfgs, ssbroyden, bfgs"),
        ("module.anchor_state_weight=[1,0]", "module.anchor_state_weight=[1, 0]: expected null or a non-empty list"),
        ("data.val_episodes=1", "data.val_episodes=1: expected a finite number in (0, 1)"),
        ("data.adaptive_pool=1", "data.adaptive_pool=1: expected 0 (off) or an integer >= 2"),
        ("data.logs=log.npz", "data.logs='log.npz': expected a list, each entry a non-empty string"),
        ("data.t_high=0", "data.t_high=0: expected a finite number > 0 or null"),
        ("+data.n_points=5", "unknown setting 'data.n_points' of data=collocation; expected one of ['_target_'"),
    ],
)
def test_each_training_setting_is_checked_by_its_field(capsys, arg, line) -> None:
    with pytest.raises(SystemExit) as stop:
        check_choices("pinnmpc.train", ["seed=1", arg])
    said = capsys.readouterr().err.strip().splitlines()
    assert stop.value.code == 2 and len(said) == 1 and said[0].startswith(f"pinnmpc.train: error: {line}"), said


def test_good_training_settings_pass_and_other_commands_are_left_to_their_checks(capsys) -> None:
    good = [
        "module.kinematic_weight=10", "module.robust_delta=null", "module.anchor_state_weight=[1,2,3,4]",
        "module.residual_scale=[1,2,3,4]", "module.optimizer=lbfgs,ssbfgs", "data.t_high=0.2",
        "data.resample_epochs=[8000]", "data.logs=[a.npz]", "data.n_collocation=${oc.env:N}", "module=pinn",
    ]  # fmt: skip
    check_choices("pinnmpc.train", good)
    check_choices("pinnmpc.closed_loop", ["plant.rtol=1e-4", "--config-dir", str(CONF)])  # plant: as before
    assert capsys.readouterr().err == ""


def test_a_job_checks_the_composed_settings_too(make_cfg) -> None:
    """A value that reaches the job another way (a Python caller's config) is refused there, in one line."""
    for override, message in [
        ("module.lbfgs_max_iter=0", "module.lbfgs_max_iter=0: expected an integer >= 1"),
        ("data.n_anchor=-1", "data.n_anchor=-1: expected an integer >= 0"),
        ("module.anchor_state_weight=[1]", "module.anchor_state_weight=[1.0]: expected null or a list of 4 entries"),
    ]:
        with pytest.raises(SettingError) as e:
            validate_train(make_cfg("train", [override]), PowerCube())
        assert str(e.value).startswith(message) and "\n" not in str(e.value)
