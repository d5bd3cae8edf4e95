"""The calibrated URDF, as the run shipped it (provenance block included).

``calibrated.urdf`` is already the ecosystem format (MoveIt's
``robot_description``, ``robot_state_publisher``, any URDF reader): the
identified geometry folded into the joint origins, joint zero offsets as
origin rotations about the joint axes, and the ``virtual_pin`` link
(``pipeline.kinematics.urdf_write``). Exporting it is a copy; the provenance
block (``pipeline.export.provenance``) travels with it.
"""

from __future__ import annotations

from pipeline.export.calibration import RunCalibration


def urdf_text(cal: RunCalibration) -> str:
    """The shipped ``calibrated.urdf`` text, unchanged."""
    return cal.calibrated_urdf
