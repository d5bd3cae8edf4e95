"""URDF reading: joints of a robot description and the serial chain between two links.

Only what kinematics needs is interpreted (joint type, parent, child, origin,
axis, limits) plus each link's ``<inertial>`` mass and centre of mass where the
URDF gives one (the gravity load of the elastic error models,
:mod:`pipeline.models.elastic`); the calibrated-URDF writer (:mod:`pipeline.kinematics.urdf_write`)
edits the original XML so that everything else survives untouched.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, field

import numpy as np

from pipeline.errors import BadInput
from pipeline.kinematics.se3 import F64, transform_from_xyz_rpy

SUPPORTED_TYPES = ("revolute", "continuous", "prismatic", "fixed")

#: the byte-order mark a Windows editor puts before a UTF-8 text file, decoded
BOM = "\ufeff"


def urdf_text(xml: str) -> str:
    """URDF text without a leading byte-order mark and blank lines.

    A URDF saved with a UTF-8 BOM and published as a ``std_msgs/String``
    keeps the mark as the first character of the text. ElementTree parses
    it, but any text written back around the root element would carry it
    into the middle of the file (after a new XML declaration), where it
    makes the XML malformed; so it is dropped where a URDF is read.
    """
    return xml.lstrip(" \t\r\n" + BOM)


@dataclass(frozen=True)
class Joint:
    """One URDF joint.

    Attributes
    ----------
    name, type, parent, child : str
        As in the URDF (``type`` one of ``revolute``, ``continuous``,
        ``prismatic``, ``fixed``, ``floating``, ``planar``).
    T_parent_joint : (4, 4)
        The ``<origin>``: joint frame expressed in the parent link frame.
    axis : (3,)
        Unit joint axis in the joint frame (URDF default ``(1, 0, 0)``).
    lower, upper : float
        Position limits (``-inf``/``inf`` for continuous or fixed joints).
    """

    name: str
    type: str
    parent: str
    child: str
    T_parent_joint: F64 = field(repr=False)
    axis: F64
    lower: float = -np.inf
    upper: float = np.inf

    @property
    def actuated(self) -> bool:
        return self.type in ("revolute", "continuous", "prismatic")


@dataclass(frozen=True)
class Inertial:
    """A link's ``<inertial>``: what gravity acts on (the inertia tensor is not read).

    Attributes
    ----------
    mass : float
        ``<mass value>``, kg (finite, >= 0).
    com : (3,)
        Centre of mass in the link frame, m: the ``<inertial><origin xyz>``
        (its ``rpy`` orients the inertia tensor only).
    """

    mass: float
    com: F64


@dataclass(frozen=True)
class RobotDescription:
    """All joints of a URDF, keyed by name, plus the link names.

    ``inertials`` holds the ``<inertial>`` of each link that has one (empty when
    the URDF carries none).
    """

    name: str
    joints: dict[str, Joint]
    links: tuple[str, ...]
    xml: str = field(repr=False)
    inertials: dict[str, Inertial] = field(default_factory=dict, repr=False, compare=False)


def _floats(text: str | None, default: tuple[float, ...], what: str) -> F64:
    if text is None:
        return np.array(default, dtype=float)
    try:
        vals = [float(x) for x in text.split()]
    except ValueError as exc:
        raise BadInput(f"URDF: {what} {text!r} is not a list of numbers") from exc
    if len(vals) != len(default) or not np.all(np.isfinite(vals)):
        raise BadInput(f"URDF: {what} {text!r} needs {len(default)} finite numbers")
    return np.array(vals, dtype=float)


def parse_urdf(xml: str) -> RobotDescription:
    """Parse URDF XML into joints and links.

    Raises
    ------
    BadInput
        If the XML does not parse or a joint is malformed.
    """
    try:
        root = ET.fromstring(urdf_text(xml))
    except ET.ParseError as exc:
        raise BadInput(f"URDF does not parse: {exc}") from exc
    if root.tag != "robot":
        raise BadInput(f"URDF root element is <{root.tag}>, expected <robot>")
    links = tuple(str(el.get("name")) for el in root.findall("link"))
    inertials = {str(el.get("name")): _inertial(el) for el in root.findall("link")}
    joints: dict[str, Joint] = {}
    for el in root.findall("joint"):
        name = el.get("name")
        jtype = el.get("type")
        parent = el.find("parent")
        child = el.find("child")
        if not name or not jtype or parent is None or child is None:
            raise BadInput(f"URDF: joint {name!r} lacks a name, type, parent or child")
        origin = el.find("origin")
        xyz = _floats(origin.get("xyz") if origin is not None else None, (0, 0, 0), f"{name} xyz")
        rpy = _floats(origin.get("rpy") if origin is not None else None, (0, 0, 0), f"{name} rpy")
        axis_el = el.find("axis")
        axis = _floats(
            axis_el.get("xyz") if axis_el is not None else None, (1, 0, 0), f"{name} axis"
        )
        norm = float(np.linalg.norm(axis))
        if jtype != "fixed" and norm < 1e-12:
            raise BadInput(f"URDF: joint {name} has a zero axis")
        axis = axis / norm if norm > 0 else axis
        lower, upper = -np.inf, np.inf
        lim = el.find("limit")
        if jtype in ("revolute", "prismatic") and lim is not None:
            lower = float(lim.get("lower", "0"))
            upper = float(lim.get("upper", "0"))
        joints[name] = Joint(
            name=name,
            type=jtype,
            parent=str(parent.get("link")),
            child=str(child.get("link")),
            T_parent_joint=transform_from_xyz_rpy(xyz, rpy),
            axis=axis,
            lower=lower,
            upper=upper,
        )
    return RobotDescription(
        name=str(root.get("name", "")),
        joints=joints,
        links=links,
        xml=xml,
        inertials={k: v for k, v in inertials.items() if v is not None},
    )


def _inertial(link: ET.Element) -> Inertial | None:
    """A ``<link>``'s ``<inertial>`` mass and centre of mass, or None without one.

    Raises
    ------
    BadInput
        If the ``<inertial>`` has no ``<mass value>`` or it is negative or not finite.
    """
    el = link.find("inertial")
    if el is None:
        return None
    name = link.get("name")
    mass_el = el.find("mass")
    text = mass_el.get("value") if mass_el is not None else None
    if text is None:
        raise BadInput(f"URDF: link {name}'s <inertial> has no <mass value>")
    mass = float(_floats(text, (0.0,), f"{name} mass")[0])
    if mass < 0:
        raise BadInput(f"URDF: link {name}'s mass {text!r} is negative")
    origin = el.find("origin")
    com = _floats(origin.get("xyz") if origin is not None else None, (0, 0, 0), f"{name} com")
    return Inertial(mass=mass, com=com)


def carried_inertials(robot: RobotDescription, path: list[Joint]) -> dict[str, Inertial]:
    """The inertial each link of a serial chain carries rigidly, off-chain bodies included.

    For every link below the chain's joints (the child of each joint of ``path``),
    its own ``<inertial>`` merged with those of the links hanging off it that are
    not on the chain (a hand's fingers, a tool beyond the tip link), through
    their joints at zero position: total mass and mass-weighted centre of mass,
    in the link's frame. A link whose subtree holds no inertial is left out, so
    a URDF without inertials gives ``{}``.
    """
    if not robot.inertials:
        return {}
    on_chain = {j.name for j in path}
    below: dict[str, list[Joint]] = {}
    for j in robot.joints.values():
        below.setdefault(j.parent, []).append(j)
    out: dict[str, Inertial] = {}
    for link in (j.child for j in path):
        mass, moment, found = 0.0, np.zeros(3), False
        stack: list[tuple[str, F64]] = [(link, np.eye(4))]
        while stack:
            name, T = stack.pop()
            inertial = robot.inertials.get(name)
            if inertial is not None:
                found = True
                mass += inertial.mass
                moment += inertial.mass * (T[:3, :3] @ inertial.com + T[:3, 3])
            for j in below.get(name, []):
                if j.name not in on_chain:
                    stack.append((j.child, T @ j.T_parent_joint))
        if found:
            com = moment / mass if mass > 0 else np.zeros(3)
            out[link] = Inertial(mass=mass, com=com)
    return out


def chain_joints(robot: RobotDescription, base_link: str, tip_link: str) -> list[Joint]:
    """Joints from ``base_link`` to ``tip_link`` in order (base first).

    Walks from the tip towards the root along each link's unique parent joint.

    Raises
    ------
    BadInput
        If a link is missing, the tip does not descend from the base, a link
        has two parent joints, or a joint on the way is of an unsupported type.
    """
    known = (
        set(robot.links)
        | {j.child for j in robot.joints.values()}
        | {j.parent for j in robot.joints.values()}
    )
    for link in (base_link, tip_link):
        if link not in known:
            raise BadInput(
                f"URDF {robot.name!r}: link {link!r} not found (links: {', '.join(robot.links)})"
            )
    parent_of: dict[str, Joint] = {}
    for j in robot.joints.values():
        if j.child in parent_of:
            raise BadInput(
                f"URDF {robot.name!r}: link {j.child!r} has two parent joints "
                f"({parent_of[j.child].name}, {j.name}); not a tree"
            )
        parent_of[j.child] = j
    path: list[Joint] = []
    link = tip_link
    while link != base_link:
        if link not in parent_of:
            raise BadInput(
                f"URDF {robot.name!r}: {tip_link!r} is not below {base_link!r}; "
                "no serial chain joins them"
            )
        j = parent_of[link]
        if j.type not in SUPPORTED_TYPES:
            raise BadInput(
                f"URDF {robot.name!r}: joint {j.name!r} of type {j.type!r} is not supported"
            )
        path.append(j)
        link = j.parent
        if len(path) > len(robot.joints):
            raise BadInput(f"URDF {robot.name!r}: cycle above link {tip_link!r}")
    return path[::-1]
