"""Calibrated URDF writer: the nominal XML with new joint origins and a virtual pin.

The original document is edited in place (ElementTree, comments kept), so that
visuals, collisions, limits, inertias and every link or joint not named stay as
they were. Only the ``<origin>`` of the named joints changes, and one fixed joint
``virtual_pin_joint`` from the flange link to a new link ``virtual_pin`` is
added (or replaced, if the input already has one). The robot's ``name`` becomes
:func:`calibrated_name` of the nominal one (``lrmate_nominal`` ->
``lrmate_calibrated``), so a calibrated file never says "nominal".

Joint zero offsets are not a URDF concept: an identified offset ``dq0`` of a
revolute joint is folded into its origin as ``T_parent_joint' = T_parent_joint
@ Rot(axis, dq0)`` by the error model before it reaches this writer, which only
sees the final ``4 x 4`` origins.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from collections.abc import Mapping

import numpy as np
from numpy.typing import ArrayLike

from pipeline.errors import BadInput
from pipeline.kinematics.se3 import F64, rpy_from_matrix
from pipeline.kinematics.urdf import urdf_text

PIN_JOINT = "virtual_pin_joint"


def calibrated_name(name: str | None) -> str:
    """The calibrated robot's name: ``nominal`` dropped, ``_calibrated`` appended once.

    ``"ur5e_nominal"`` -> ``"ur5e_calibrated"``, ``"ur5e"`` -> ``"ur5e_calibrated"``,
    ``"ur5e_calibrated"`` stays (a recalibration), ``""`` -> ``"calibrated"``.
    """
    base = re.sub(r"[_\-\s]*nominal[_\-\s]*", "_", name or "", flags=re.IGNORECASE).strip("_")
    if base.endswith("calibrated"):
        return base
    return f"{base}_calibrated" if base else "calibrated"


def _fmt(values: ArrayLike) -> str:
    """Space-separated floats with round-trip precision (``repr``)."""
    return " ".join(repr(float(v)) for v in np.asarray(values, dtype=float).ravel())


def _set_origin(joint_el: ET.Element, T: F64) -> None:
    """Replace (or add) the ``<origin>`` of a joint element with ``T`` as xyz/rpy."""
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"origin of joint {joint_el.get('name')!r} must be a finite 4x4 matrix")
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-9):
        raise ValueError(f"origin of joint {joint_el.get('name')!r} is not a rigid transform")
    origin = joint_el.find("origin")
    if origin is None:
        origin = ET.Element("origin")
        joint_el.insert(0, origin)
    origin.set("xyz", _fmt(T[:3, 3]))
    origin.set("rpy", _fmt(rpy_from_matrix(R)))


def write_calibrated_urdf(
    urdf_xml: str,
    origins: Mapping[str, ArrayLike],
    flange_link: str,
    p_flange_pin: ArrayLike,
    pin_link: str = "virtual_pin",
) -> str:
    """Return the URDF with new joint origins and a fixed virtual-pin link.

    Parameters
    ----------
    urdf_xml : str
        The nominal URDF document.
    origins : {joint name: (4, 4)}
        New ``T_parent_joint`` of each named joint (rigid). Written as URDF
        ``xyz`` and fixed-axis ``rpy`` (``R = Rz(y) Ry(p) Rx(r)``), full
        ``repr`` precision so the file reproduces the FK to ~1e-15.
    flange_link : str
        Link the pin is fixed to.
    p_flange_pin : (3,)
        Virtual-pin point in the flange frame, metres.
    pin_link : str
        Name of the new link (default ``virtual_pin``).

    Returns
    -------
    str
        The edited XML (with an XML declaration).

    Raises
    ------
    BadInput
        If the XML does not parse, a named joint or the flange link is missing,
        or ``pin_link`` names an existing link not created by a previous write.
    """
    urdf_xml = urdf_text(urdf_xml)
    parser = ET.XMLParser(target=ET.TreeBuilder(insert_comments=True))
    try:
        root = ET.fromstring(urdf_xml, parser=parser)
    except ET.ParseError as exc:
        raise BadInput(f"URDF does not parse: {exc}") from exc
    joints = {el.get("name"): el for el in root.findall("joint")}
    links = {el.get("name"): el for el in root.findall("link")}
    missing = sorted(set(origins) - set(joints))
    if missing:
        raise BadInput(f"URDF has no joint(s) {missing} to write calibrated origins into")
    child_links = {c.get("link") for el in joints.values() if (c := el.find("child")) is not None}
    if flange_link not in links and flange_link not in child_links:
        raise BadInput(f"URDF has no link {flange_link!r} to fix the virtual pin to")
    for name, T in origins.items():
        _set_origin(joints[name], np.asarray(T, dtype=float))
    root.set("name", calibrated_name(root.get("name")))

    # Drop a virtual pin a previous calibration left, then add the new one.
    old = joints.get(PIN_JOINT)
    if old is not None:
        root.remove(old)
    if pin_link in links:
        if old is None:
            raise BadInput(f"URDF already has a link {pin_link!r} not made by {PIN_JOINT!r}")
        root.remove(links[pin_link])
    p = np.asarray(p_flange_pin, dtype=float).reshape(3)
    if not np.all(np.isfinite(p)):
        raise ValueError("virtual-pin point must be finite")
    if len(root) and not (root[-1].tail or "").strip():
        root[-1].tail = "\n  "
    comment = ET.Comment(
        " virtual pin identified by vtcal: the touch-up point in the flange frame "
    )
    root.append(comment)
    link = ET.SubElement(root, "link", {"name": pin_link})
    j = ET.SubElement(root, "joint", {"name": PIN_JOINT, "type": "fixed"})
    ET.SubElement(j, "parent", {"link": flange_link})
    ET.SubElement(j, "child", {"link": pin_link})
    ET.SubElement(j, "origin", {"xyz": _fmt(p), "rpy": "0 0 0"})
    comment.tail = link.tail = "\n  "
    j.tail = "\n"
    # ElementTree drops what surrounds the root element: keep the original prolog
    # (XML declaration, comments) and epilog verbatim.
    m = re.search(r"<robot[\s>]", urdf_xml)
    prolog = urdf_xml[: m.start()] if m else ""
    if not prolog.lstrip().startswith("<?xml"):
        prolog = '<?xml version="1.0"?>\n' + prolog
    end = urdf_xml.rfind("</robot>")
    epilog = urdf_xml[end + len("</robot>") :] if end >= 0 else "\n"
    return prolog + ET.tostring(root, encoding="unicode") + (epilog or "\n")
