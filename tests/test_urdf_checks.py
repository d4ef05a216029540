"""A user's own URDF: what pinnmpc cannot model is refused at load in one line, and what it can is modelled right
(joint order, axis length) by every backend alike, checked against Pinocchio on the original file."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import torch
from omegaconf import OmegaConf

from pinnmpc.surrogate import CheckpointError, Surrogate, load_surrogate
from pinnmpc.surrogate.prior import ArmPrior
from pinnmpc.systems import Box, RigidArm, build_system, load_system
from pinnmpc.systems.urdf import URDF_DIR
from pinnmpc.training.models import fresh_model

LIMIT = '<limit lower="-3" upper="3" effort="50" velocity="3"/>'
LINK = '<link name="{0}"><inertial><origin xyz="{1} 0 0"/><mass value="{2}"/><inertia ixx="0.001" ixy="0" ixz="0" iyy="{3}" iyz="0" izz="{3}"/></inertial></link>'  # noqa: E501


def _joint(name: str, parent: str, child: str, x: float = 0.0, kind: str = "revolute", axis: str = "0 0 1",
           extra: str = LIMIT) -> str:  # fmt: skip
    """One joint element (a limit tag unless extra says otherwise)."""
    return (f'<joint name="{name}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>'
            f'<origin xyz="{x} 0 0"/><axis xyz="{axis}"/>{extra}</joint>')  # fmt: skip


def _urdf(tmp_path: Path, *, j2: dict | None = None, tip_mass: float = 1.0, extra: str = "") -> Path:
    """A two-link arm (joints j1, j2 about z, gravity set by the arm), with j2's attributes and more parts varied."""
    parts = ['<link name="base"/>', _joint("j1", "base", "l1"), LINK.format("l1", 0.2, 2.0, 0.03)]
    parts += [_joint("j2", "l1", "l2", 0.4, **(j2 or {})), LINK.format("l2", 0.15, tip_mass, 0.01 * tip_mass), extra]
    path = tmp_path / "arm.urdf"
    path.write_text('<?xml version="1.0"?><robot name="arm">' + "".join(parts) + "</robot>")
    return path


def _arm(urdf: Path, joints: tuple[str, ...] = ("j1", "j2"), **kw: object) -> RigidArm:
    """The arm with torque actuation and friction on both joints, gravity in the plane of motion."""
    box = Box((-3.0, -3.0, -3.0, -3.0), (3.0, 3.0, 3.0, 3.0))
    spec = {"name": "arm", "urdf": str(urdf), "joints": joints, "tau": 0.1, "gravity": (0.0, -9.81, 0.0),
            "viscous": (2.0, 1.0), "coulomb": (0.3, 0.1), "state_box": box,
            "input_box": Box((-9.0, -9.0), (9.0, 9.0))}  # fmt: skip
    return RigidArm(**{**spec, **kw})


def _pinocchio_rhs(urdf: Path, arm: RigidArm, x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """dx/dt from Pinocchio on the original file, joints mapped by name: the golden."""
    model = pin.buildModelFromUrdf(str(urdf))
    model.gravity.linear = np.array(arm.gravity)
    data, n = model.createData(), arm.nq
    idx = [model.idx_qs[model.getJointId(j)] for j in arm.joints]
    q, v = np.zeros(model.nq), np.zeros(model.nv)
    q[idx], v[idx] = x[:n], x[n:]
    tau = np.zeros(model.nv)
    tau[idx] = arm.actuation_torque(x[n:], u)
    return np.concatenate((x[n:], pin.aba(model, data, q, v, tau)[idx]))


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"j2": {"kind": "prismatic", "axis": "1 0 0"}}, "joint 'j2' is prismatic; expected revolute joints"),
        ({"j2": {"kind": "continuous", "extra": ""}}, "joint 'j2' is continuous; expected revolute joints"),
        ({"j2": {"extra": '<limit lower="-1" upper="1"/>'}}, "joint 'j2' has no <limit> effort velocity"),
        ({"j2": {"extra": LIMIT + '<mimic joint="j1"/>'}}, "joint 'j2' mimics 'j1'; expected independent joints"),
        ({"j2": {"axis": "0 0 0"}}, "<axis xyz='0 0 0'>; expected three numbers, not all zero"),
        ({"tip_mass": 0.0}, "the mass matrix is singular at q=[0.0, 0.0] (joints ['j2'] move no mass"),
        (
            {"extra": _joint("free", "l2", "l3", kind="floating", extra="") + '<link name="l3"/>'},
            "joint 'free' is floating; expected a fixed-base arm",
        ),
    ],
)
def test_what_pinnmpc_cannot_model_is_refused_at_load(tmp_path: Path, change: dict, message: str) -> None:
    with pytest.raises(ValueError) as e:
        _arm(_urdf(tmp_path, **change))
    assert message in str(e.value) and "\n" not in str(e.value)


def test_a_name_that_cannot_name_c_functions_and_a_missing_tip_frame_are_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="system name 'my-arm'; expected letters, digits and _"):
        _arm(_urdf(tmp_path), name="my-arm")
    with pytest.raises(ValueError, match="tip_frame='hand' is not a frame of"):
        _arm(_urdf(tmp_path), tip_frame="hand")


@pytest.mark.parametrize(("joints", "axis"), [(("j2", "j1"), "0 0 1"), (("j1", "j2"), "0 0 2.5")])
def test_joint_order_and_axis_length_are_modelled_as_pinocchio_reads_the_file(
    tmp_path: Path, joints: tuple[str, ...], axis: str
) -> None:
    urdf = _urdf(tmp_path, j2={"axis": axis})
    arm = _arm(urdf, joints)
    rng = np.random.default_rng(3)
    x, u = rng.uniform(-2.0, 2.0, (6, 4)), rng.uniform(-5.0, 5.0, (6, 2))
    golden = np.stack([_pinocchio_rhs(urdf, arm, xi, ui) for xi, ui in zip(x, u)])
    np.testing.assert_allclose(arm.rhs(x, u), golden, rtol=1e-10, atol=1e-10)  # the plant
    torch_rhs = arm.rhs(torch.from_numpy(x), torch.from_numpy(u)).numpy()
    np.testing.assert_allclose(torch_rhs, golden, rtol=1e-10, atol=1e-10)  # training, the controllers


def test_a_users_arm_loads_by_path_and_its_prior_is_its_own(tmp_path: Path) -> None:
    urdf = _urdf(tmp_path)
    yaml = tmp_path / "planar3.yaml"  # the name of a shipped arm, another URDF
    yaml.write_text(
        "dynamics:\n  _target_: pinnmpc.systems.RigidArm\n  _convert_: all\n  name: planar3\n"
        f"  urdf: {urdf}\n  joints: [j1, j2]\n  tau: 0.1\n  gravity: [0.0, -9.81, 0.0]\n  viscous: [2.0, 1.0]\n"
        "  coulomb: [0.3, 0.1]\n"
        "  state_box: {_target_: pinnmpc.systems.Box, low: [-3, -3, -3, -3], high: [3, 3, 3, 3]}\n"
        "  input_box: {_target_: pinnmpc.systems.Box, low: [-9, -9], high: [9, 9]}\n"
    )
    arm = load_system(yaml)
    assert arm.urdf == str(urdf) and arm.nq == 2
    prior = ArmPrior(OmegaConf.to_container(OmegaConf.load(yaml).dynamics))  # what a network's config holds
    assert prior.arm.urdf == str(urdf) and prior.nq == 2  # not the shipped planar3
    with pytest.raises(ValueError, match="no such file; expected a system .yaml"):
        load_system(tmp_path / "nope.yaml")


def test_a_network_finds_its_arm_from_any_working_dir_and_names_it_when_gone(make_cfg, tmp_path, monkeypatch):
    (tmp_path / "arms").mkdir()
    shutil.copy(URDF_DIR / "planar3.urdf", tmp_path / "arms" / "mine.urdf")
    monkeypatch.chdir(tmp_path)  # the user's project, with its URDF given relative to it
    cfg = make_cfg("train", ["system=planar3", "system.dynamics.urdf=arms/mine.urdf", "model.hidden=[8]"])
    system = build_system(cfg.system)
    cfg.model.output_scale = [1.0] * 6  # no flow estimate needed here
    net = Surrogate(fresh_model(cfg, system), system.tau, system.state_names, system.input_names)
    path = net.save(tmp_path / "mine.pt")
    monkeypatch.chdir("/")
    assert load_surrogate(path).model.prior.arm.urdf == str(tmp_path / "arms" / "mine.urdf")
    (tmp_path / "arms" / "mine.urdf").rename(tmp_path / "arms" / "moved.urdf")
    with pytest.raises(CheckpointError, match=r"mine.pt: its prior's arm is gone \(urdf=.*mine.urdf: no such file;"):
        load_surrogate(path)
