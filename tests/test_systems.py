"""Robots as data: every arm against its Pinocchio goldens on every path, configs compose, planar3 end to end."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf

from pinnmpc import load_surrogate, load_system
from pinnmpc.plant.integrators import rk4_step
from pinnmpc.systems import Box, PowerCube, RigidArm, available, build_system
from pinnmpc.training.job_settings import validate_train

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"
SHIPPED = ROOT / "pinnmpc" / "checkpoints"
SHARED = ROOT.parent / "shared"
ARMS = ("planar3", "panda")


def _golden(name: str) -> dict[str, np.ndarray]:
    path = SHARED / "systems" / name / "golden.npz"
    if not path.is_file():
        pytest.skip(f"golden values not available at {path}")
    return dict(np.load(path))


def _rel(got: np.ndarray, want: np.ndarray) -> float:
    return float((np.abs(got - want) / (1 + np.abs(want))).max())


@pytest.mark.parametrize("name", ARMS)
def test_arm_matches_golden_on_every_path(name: str) -> None:
    d, arm = _golden(name), load_system(name)
    x, u = torch.tensor(d["x"]), torch.tensor(d["u"])
    assert _rel(arm.rhs(x, u).numpy(), d["dxdt"]) < 1e-9  # adam, torch
    assert _rel(arm.rhs(d["x"], d["u"]), d["dxdt"]) < 1e-9  # Pinocchio ABA, batched numpy
    assert _rel(np.stack([arm.rhs(xi, ui) for xi, ui in zip(d["x"], d["u"])]), d["dxdt"]) < 1e-9  # the plant's path
    assert _rel(arm.fast_rhs(x, u).numpy(), d["dxdt"]) < 1e-9  # compiled CasADi
    f = arm.casadi_rhs()
    assert _rel(np.stack([f(xi, ui).full().ravel() for xi, ui in zip(d["x"], d["u"])]), d["dxdt"]) < 1e-9
    assert arm.tau == float(d["step_tau"])
    np.testing.assert_allclose(arm.state_box.low, d["state_low"])
    np.testing.assert_allclose(arm.state_box.high, d["state_high"])
    np.testing.assert_allclose(arm.input_box.low, d["input_low"])
    np.testing.assert_allclose(arm.input_box.high, d["input_high"])


@pytest.mark.parametrize("name", ARMS)
def test_one_period_flow_matches_golden(name: str) -> None:
    d, arm = _golden(name), load_system(name)
    x1 = rk4_step(arm.fast_rhs, torch.tensor(d["step_x0"]), torch.tensor(d["step_u"]), arm.tau, 2.5e-5)
    assert _rel(x1.numpy(), d["step_x1"]) < 1e-7  # stiff friction: RK4 needs small steps to match DOP853


def test_powercube_system_is_the_stable_rhs() -> None:
    cube = load_system("powercube")
    g = torch.Generator().manual_seed(0)
    x, u = torch.randn(16, 4, generator=g, dtype=torch.float64), torch.randn(16, 2, generator=g, dtype=torch.float64)
    assert torch.equal(cube.rhs(x, u), PowerCube().rhs(x, u))
    f = cube.casadi_rhs()
    got = np.stack([f(xi, ui).full().ravel() for xi, ui in zip(x.numpy(), u.numpy())])
    np.testing.assert_allclose(got, PowerCube().rhs(x, u).numpy(), rtol=1e-13, atol=1e-12)
    path = SHARED / "powercube" / "golden.npz"
    if path.is_file():
        d = np.load(path)
        assert np.abs(cube.rhs(torch.tensor(d["x"]), torch.tensor(d["u"])).numpy() - d["dxdt"]).max() < 1e-10


@pytest.mark.parametrize("name", ARMS)
def test_compiled_gradient_equals_autograd_through_adam(name: str) -> None:
    arm = load_system(name)
    g = torch.Generator().manual_seed(1)
    low, high = torch.tensor(arm.state_box.low), torch.tensor(arm.state_box.high)
    x = (low + (high - low) * torch.rand(4, 2 * arm.nq, generator=g, dtype=torch.float64)).requires_grad_(True)
    u = torch.rand(4, arm.nq, generator=g, dtype=torch.float64).requires_grad_(True)
    w = torch.randn(4, 2 * arm.nq, generator=g, dtype=torch.float64)
    gx, gu = torch.autograd.grad((arm.fast_rhs(x, u) * w).sum(), (x, u))
    ax, au = torch.autograd.grad((arm.rhs(x, u) * w).sum(), (x, u))
    torch.testing.assert_close(gx, ax, rtol=1e-8, atol=1e-8)
    torch.testing.assert_close(gu, au, rtol=1e-8, atol=1e-8)


@pytest.mark.parametrize("name", ["powercube", *ARMS])
def test_mismatch_changes_the_plant_and_one_is_nominal(name: str) -> None:
    arm = load_system(name)
    x = np.array(arm.state_box.high) * 0.3
    u = np.array(arm.input_box.high) * 0.5
    np.testing.assert_allclose(arm.with_mismatch(1.0, 1.0).rhs(x, u), arm.rhs(x, u), rtol=1e-12)
    assert not np.allclose(arm.with_mismatch(1.2, 1.0).rhs(x, u), arm.rhs(x, u))
    assert not np.allclose(arm.with_mismatch(1.0, 1.3).rhs(x, u), arm.rhs(x, u))


def test_kinematics_draws_the_arm() -> None:
    planar = load_system("planar3")
    pts = planar.kinematics(np.zeros((2, 3)))
    assert pts.shape == (2, 5, 3)
    np.testing.assert_allclose(pts[:, 0], 0.0)
    np.testing.assert_allclose(pts[..., 2], 0.0)  # a planar arm draws in the z = 0 plane
    np.testing.assert_allclose(np.linalg.norm(np.diff(pts[0, 1:4], axis=0), axis=1), [0.4, 0.35], atol=1e-12)
    panda = load_system("panda")
    q = (np.array(panda.state_box.low[:7]) + np.array(panda.state_box.high[:7])) / 2
    pts = panda.kinematics(q[None])
    assert pts.shape == (1, 9, 3) and np.ptp(pts[..., 2]) > 0.1  # a 3-D arm


def test_systems_are_found_by_name() -> None:
    assert {"powercube", "planar3", "panda"} <= set(available())
    with pytest.raises(ValueError, match="system='nope'.*expected one of"):
        load_system("nope")


def _planar3(**changes: object) -> RigidArm:
    base = dict(
        name="planar3",
        urdf="planar3.urdf",
        tau=0.1,
        state_box=Box([-3.0] * 6, [3.0] * 6),
        input_box=Box([-1.0] * 3, [1.0] * 3),
        viscous=[1.0, 1.0, 1.0],
        coulomb=[0.0, 0.0, 0.0],
    )
    return RigidArm(**{**base, **changes})


@pytest.mark.parametrize(
    ("changes", "fragment"),
    [
        ({"urdf": "missing.urdf"}, "urdf=missing.urdf: no such file"),
        ({"joints": ["joint1", "elbow"]}, r"\['elbow'\] not movable joints of planar3.urdf"),
        ({"viscous": [1.0, 2.0]}, r"viscous=\[1.0, 2.0\]; expected 3 finite numbers"),
        ({"state_box": Box([-1.0] * 4, [1.0] * 4)}, "state_box has 4 and input_box 3 entries; expected 6 and 3"),
        ({"actuation": "pneumatic"}, "actuation='pneumatic'; expected one of"),
        ({"tau": 0.0}, "need tau > 0"),
    ],
)
def test_bad_arm_settings_name_the_setting(changes: dict, fragment: str) -> None:
    with pytest.raises((ValueError, FileNotFoundError), match=fragment) as info:
        _planar3(**changes)
    assert "\n" not in str(info.value)


# ---------------------------------------------------------------------------------------------------------------
# Every config composes, resolves and instantiates, for every system


GROUP_OPTIONS = {
    "controller": sorted(p.stem for p in (CONF / "controller").glob("*.yaml")),  # every one there
    "reference": ["builtin"],
    "experiment": ["paper", "planar3", "panda", "panda-moving", "panda-frozen", "panda-gpu"],
}


@pytest.mark.parametrize("system", ["powercube", "planar3", "panda"])
@pytest.mark.parametrize(
    "entry", ["train", "closed_loop", "self_loop", "residuals", "time_basis", "capacity", "robustness", "bench"]
)
def test_every_config_composes_and_instantiates(entry: str, system: str) -> None:
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(entry, overrides=[f"system={system}"])
        OmegaConf.to_container(cfg, resolve=True)
        arm = build_system(cfg.system)
        assert arm.name == system and len(cfg.system.control.Q) == 2 * arm.nq
        if entry == "train":
            instantiate(cfg.trainer, logger=False, enable_checkpointing=False)
            for group, options in GROUP_OPTIONS.items():
                for option in options if group == "experiment" else []:
                    OmegaConf.to_container(compose(entry, [f"system={system}", f"{group}={option}"]), resolve=True)
        if entry == "closed_loop":
            for option in GROUP_OPTIONS["controller"]:
                c = compose(entry, [f"system={system}", f"controller={option}"])
                OmegaConf.to_container(c, resolve=True)


def _differences(shipped: dict, composed: dict, where: str = "") -> list[str]:
    """Keys whose value the shipped network's recorded config and a composed one disagree on (keys in both)."""
    out = []
    for key in shipped.keys() & composed.keys():
        a, b = shipped[key], composed[key]
        if isinstance(a, dict) and isinstance(b, dict):
            out += _differences(a, b, f"{where}{key}.")
        elif a != b:
            out.append(f"{where}{key}: shipped {a!r}, composed {b!r}")
    return out


@pytest.mark.parametrize("name", ["planar3", "panda", "panda-frozen"])
def test_each_shipped_networks_experiment_is_its_recipe(name: str) -> None:
    recorded = load_surrogate(SHIPPED / f"{name}.pt").meta["config"]
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = OmegaConf.to_container(compose("train", [f"experiment={name}"]), resolve=True)
    sections = ("system", "model", "data", "module", "trainer", "tau", "t_max", "seed", "stage")
    if recorded.get("init_from"):  # its last phase went on from another network: that phase's own budget
        assert recorded["trainer"]["max_time"] in load_surrogate(SHIPPED / f"{name}.pt").meta["trained_with"]
        cfg["trainer"]["max_time"] = recorded["trainer"]["max_time"]
    assert _differences({k: recorded[k] for k in sections if k in recorded}, cfg) == []  # tau: older configs only
    assert cfg["data"]["n_anchor"] > 4000  # not the defaults: the recipe is what `make train system=<arm>` lacks


def test_the_panda_gpu_recipe_is_the_frozen_prior_ones_with_more_points_on_a_gpu() -> None:
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cpu = OmegaConf.to_container(compose("train", ["experiment=panda-frozen"]), resolve=True)
        composed = compose("train", ["experiment=panda-gpu"])
        gpu = OmegaConf.to_container(composed, resolve=True)
    validate_train(composed, load_system("panda"))  # threads=0 (every core) is a valid setting of a training
    assert sorted(_differences(cpu, gpu)) == [
        "data.n_anchor: shipped 16000, composed 64000",
        "data.n_collocation: shipped 20000, composed 80000",
        "threads: shipped 2, composed 0",
        "trainer.accelerator: shipped 'cpu', composed 'auto'",
    ]


# ---------------------------------------------------------------------------------------------------------------
# planar3 end to end: real training steps, the real plant, a real closed loop


def test_planar3_trains_and_tracks(make_cfg, tmp_path: Path) -> None:
    from pinnmpc.simulation.run import run_closed_loop
    from pinnmpc.training.run import train

    overrides = [
        "system=planar3",
        "data.n_collocation=256",
        "data.n_val=32",
        "data.n_anchor=32",
        "module.lbfgs_max_iter=3",
        "trainer.max_epochs=2",
        "trainer.check_val_every_n_epoch=1",
        "model.auto_scale.samples=64",
        "self_loop_figure.every_n_epochs=0",
        "threads=1",
        "progress=false",
    ]
    train(make_cfg("train", overrides), tmp_path / "train")
    surrogate = load_surrogate(tmp_path / "train" / "surrogate.pt")
    assert surrogate.state_names == load_system("planar3").state_names
    assert surrogate.model.config["angle_sums"] == [[0, 1], [0, 1, 2], [1, 2]]  # the config's link-angle inputs
    cfg = make_cfg(
        "closed_loop",
        ["system=planar3", f"checkpoint={tmp_path / 'train' / 'surrogate.pt'}", "max_steps=6", "progress=false"],
    )
    m = run_closed_loop(cfg, tmp_path / "loop")
    assert list(m["mae"]) == list(surrogate.state_names)
    assert m["steps"] == 6 and (tmp_path / "loop" / "closed_loop.png").is_file()
    assert json.loads((tmp_path / "loop" / "metrics.json").read_text())["reference"] == "builtin:default"


def test_shipped_planar3_network_tracks_its_reference(make_cfg, tmp_path: Path) -> None:
    from pinnmpc.simulation.run import run_closed_loop

    m = run_closed_loop(make_cfg("closed_loop", ["system=planar3", "max_steps=40", "progress=false"]), tmp_path)
    assert m["status"] == "ok" and m["fallbacks"] == 0
    assert max(m["mae"][n] for n in list(m["mae"])[:3]) < 3e-3


def test_a_wrong_length_list_is_refused_when_the_arm_loads(tmp_path):
    # a new arm's config copied from planar3 with one per-joint list too short: refused by load_system already
    text = (ROOT / "conf" / "system" / "planar3.yaml").read_text()
    short = text.replace("disturbance_max: [0.05, 0.05, 0.05, 0.5, 0.5, 0.5]", "disturbance_max: [0.05, 0.05]")
    assert short != text
    (tmp_path / "arm.yaml").write_text(short)
    with pytest.raises(ValueError, match=r"disturbance_max=\[0.05, 0.05\]: expected null or a list of 6"):
        load_system(str(tmp_path / "arm.yaml"))
