"""URDF files as pinnmpc reads them: resolved, checked, joints locked, a payload added (what adam, Pinocchio and
MuJoCo load)."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pinnmpc.systems.base import Box

URDF_DIR = Path(__file__).resolve().parent / "urdf"  # URDFs shipped with the package
_JOINT_TAGS = {"origin", "parent", "child", "axis", "calibration", "dynamics", "limit", "mimic", "safety_controller"}


def resolve_urdf(path: str | Path) -> Path:
    """A URDF by absolute path, path relative to the working dir, or file name in the package's urdf folder."""
    p = Path(path).expanduser()
    for candidate in (p, URDF_DIR / p):
        if candidate.is_file():
            return candidate.resolve()
    where = "" if p.is_absolute() else f" (looked in the working dir and {URDF_DIR})"
    raise FileNotFoundError(f"urdf={path}: no such file{where}; expected a .urdf")


def portable_urdf(path: str | Path) -> str:
    """A URDF path that resolves from any working dir: a shipped file by its name, any other absolute (a relative
    path that does not resolve stays as given)."""
    try:
        resolved = resolve_urdf(path)
    except FileNotFoundError:
        return str(path)
    return resolved.name if resolved.parent == URDF_DIR.resolve() else str(resolved)


def locked_urdf(path: Path, joints: Sequence[str]) -> str:
    """URDF text with every movable joint not in `joints` made fixed at q = 0 (adam refuses prismatic joints, even
    unactuated ones, and the controlled arm holds its other joints still) and every joint axis of unit length
    (Pinocchio normalises axes, adam does not); what pinnmpc cannot model is refused here, naming the joint."""
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as e:
        raise ValueError(f"urdf={path}: not valid XML ({e})") from None
    movable = {j.get("name"): j for j in root.findall("joint") if j.get("type") not in ("fixed", "floating")}
    missing = [j for j in joints if j not in movable]
    if missing:
        raise ValueError(f"joints={list(joints)}: {missing} not movable joints of {path.name}; it has {list(movable)}")
    _refuse_unsupported(root, path, joints)
    for name, j in movable.items():
        if name not in joints:
            j.set("type", "fixed")
    for axis in root.iter("axis"):
        _unit_axis(axis, path)
    for dyn in root.iter("dynamics"):  # vendor attributes (Franka's K, D, mu_*) make URDF parsers warn per joint
        for key in [k for k in dyn.attrib if k not in ("damping", "friction")]:
            del dyn.attrib[key]
    for j in root.findall("joint"):  # and so do vendor tags (the FR3's position_based_velocity_limits)
        for child in [c for c in j if c.tag not in _JOINT_TAGS]:
            j.remove(child)
    return ET.tostring(root, encoding="unicode")


def _refuse_unsupported(root: ET.Element, path: Path, joints: Sequence[str]) -> None:
    """Fixed-base arms of revolute joints with full <limit> tags, no mimic couplings: anything else is refused."""
    for j in root.findall("joint"):
        name, kind = j.get("name"), j.get("type")
        if kind == "floating":
            raise ValueError(
                f"urdf={path}: joint {name!r} is floating; expected a fixed-base arm (pinnmpc models no base)"
            )
        mimic = j.find("mimic")
        if mimic is not None and (name in joints or mimic.get("joint") in joints):
            raise ValueError(
                f"urdf={path}: joint {name!r} mimics {mimic.get('joint')!r}; expected independent joints (mimic "
                "couplings are not modelled: leave both out of system.dynamics.joints)"
            )
        if name not in joints:
            continue
        if kind != "revolute":
            raise ValueError(
                f"urdf={path}: joint {name!r} is {kind}; expected revolute joints in system.dynamics.joints "
                "(continuous, prismatic and planar joints are not supported; leave it out to lock it at 0)"
            )
        limit = j.find("limit")
        absent = [k for k in ("lower", "upper", "effort", "velocity") if limit is None or limit.get(k) is None]
        if absent:
            raise ValueError(
                f"urdf={path}: joint {name!r} has no <limit> {' '.join(absent)}; expected <limit lower= upper= "
                "effort= velocity=> on every revolute joint (the URDF standard)"
            )


def _unit_axis(axis: ET.Element, path: Path) -> None:
    """Scale an <axis xyz> to unit length in place; a zero or malformed axis is refused."""
    try:
        xyz = [float(v) for v in (axis.get("xyz") or "1 0 0").split()]
    except ValueError:
        xyz = []
    norm = math.sqrt(sum(v * v for v in xyz)) if len(xyz) == 3 else 0.0
    if not (norm > 0 and math.isfinite(norm)):
        raise ValueError(f"urdf={path}: <axis xyz={axis.get('xyz')!r}>; expected three numbers, not all zero")
    if abs(norm - 1.0) > 1e-12:  # unit axes keep their text
        axis.set("xyz", " ".join(repr(v / norm) for v in xyz))


def urdf_joint_limits(path: Path, joints: Sequence[str]) -> Box:
    """The <limit lower upper> of each joint (-inf/inf where a joint has none, e.g. a continuous one)."""
    found = {j.get("name"): j for j in ET.parse(path).getroot().findall("joint")}
    low, high = [], []
    for name in joints:
        limit = found[name].find("limit") if found[name].get("type") != "continuous" else None
        low.append(-math.inf if limit is None or limit.get("lower") is None else float(limit.get("lower")))
        high.append(math.inf if limit is None or limit.get("upper") is None else float(limit.get("upper")))
    return Box(tuple(low), tuple(high))


def revolute_joints(path: Path) -> list[str]:
    """Revolute joints in file order: the default joint list."""
    return [j.get("name") for j in ET.parse(path).getroot().findall("joint") if j.get("type") == "revolute"]


@dataclass(frozen=True)
class Payload:
    """A point mass fixed to a link: mass in kg, pos in m in that link's frame (None: the tip drawn, as the MuJoCo
    robots' payload), link None: the tip frame's link or the last joint's child link."""

    mass: float
    pos: tuple[float, float, float] | None = None
    link: str | None = None


def _payload(name: str, value: Any, key: str = "payload") -> Payload | None:
    """A payload (or load: key) from config (a mapping) or as given, checked: mass >= 0 and finite, pos three finite
    numbers."""
    if value is None or isinstance(value, Payload):
        return value
    keys = ("mass", "pos", "link")
    if not isinstance(value, Mapping) or "mass" not in value or any(k not in keys for k in value):
        raise ValueError(
            f"{name}: {key}={value!r}; expected {{mass: kg, pos: [x, y, z] m or null, link: name or null}}"
        )
    mass, pos = value["mass"], value.get("pos")
    if isinstance(mass, bool) or not isinstance(mass, int | float) or not math.isfinite(mass) or mass < 0:
        raise ValueError(f"{name}: {key}.mass={mass!r}; expected a finite number >= 0 (kg)")
    if pos is not None:
        ok = isinstance(pos, Sequence) and not isinstance(pos, str) and len(pos) == 3
        if not ok or not all(not isinstance(v, bool) and isinstance(v, int | float) and math.isfinite(v) for v in pos):
            raise ValueError(f"{name}: {key}.pos={pos!r}; expected 3 finite numbers (m, in the link's frame) or null")
        pos = tuple(float(v) for v in pos)
    return Payload(float(mass), pos, value.get("link"))


def payload_place(
    text: str, payload: Payload, tip_frame: str | None, joints: Sequence[str]
) -> tuple[str, tuple[float, ...]]:
    """The payload's link and its position in that link's frame, the defaults resolved: the MuJoCo robots' convention
    (the tip frame's origin, else the tip drawn: twice the last link's centre of mass)."""
    root = ET.fromstring(text)
    links = {link.get("name"): link for link in root.iter("link")}
    last = next(j for j in root.findall("joint") if j.get("name") == joints[-1]).find("child").get("link")
    link = payload.link or tip_frame or last
    if link not in links:
        by_joint = {j.get("name"): j.find("child").get("link") for j in root.findall("joint")}
        if link not in by_joint:
            raise ValueError(
                f"payload.link={link!r}: neither a link nor a joint of the URDF; expected one of {list(links)}"
            )
        link = by_joint[link]
    pos = payload.pos
    if pos is None and link == last and not (payload.link or tip_frame):  # the tip drawn: twice the link's centre
        origin = links[link].find("inertial/origin")
        xyz = [float(v) for v in (origin.get("xyz") or "0 0 0").split()] if origin is not None else [0.0] * 3
        pos = tuple(2.0 * v for v in xyz)
    return link, tuple(float(v) for v in (pos or (0.0, 0.0, 0.0)))


def payload_urdf(
    text: str,
    payload: Payload,
    tip_frame: str | None,
    joints: Sequence[str],
    scale: float = 1.0,
    name: str = "pinnmpc_payload",
) -> str:
    """URDF text with the payload as a fixed child link `name` of zero inertia (mass / scale: the arm's mass_scale
    leaves it unscaled), so adam and Pinocchio see one arm; its default link and pos are the MuJoCo robots'
    convention."""
    link, pos = payload_place(text, payload, tip_frame, joints)
    root = ET.fromstring(text)
    joint = ET.SubElement(root, "joint", {"name": f"{name}_joint", "type": "fixed"})
    ET.SubElement(joint, "parent", {"link": link})
    ET.SubElement(joint, "child", {"link": name})
    ET.SubElement(joint, "origin", {"xyz": " ".join(repr(v) for v in pos), "rpy": "0 0 0"})
    inertial = ET.SubElement(ET.SubElement(root, "link", {"name": name}), "inertial")
    ET.SubElement(inertial, "origin", {"xyz": "0 0 0", "rpy": "0 0 0"})
    ET.SubElement(inertial, "mass", {"value": repr(payload.mass / scale)})
    ET.SubElement(inertial, "inertia", dict.fromkeys(("ixx", "ixy", "ixz", "iyy", "iyz", "izz"), "0"))
    return ET.tostring(root, encoding="unicode")
