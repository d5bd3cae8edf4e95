"""``vtcal export``: a run's calibration in the formats robot software loads.

One module per format, each a pure function of a
:class:`~pipeline.export.calibration.RunCalibration` (read from the run folder
by :func:`~pipeline.export.calibration.load_run`) returning the file's text:

==================  =========================================  ===============================
format              module                                     for
==================  =========================================  ===============================
``urdf``            :mod:`pipeline.export.urdf`                MoveIt, robot_state_publisher
``ur-calibration``  :mod:`pipeline.export.ur`                  UR ROS drivers, ur_description
``offsets``         :mod:`pipeline.export.offsets`             controllers with own kinematics
``dh``              :mod:`pipeline.export.dh`                  DH-based tools and controllers
``json``            :mod:`pipeline.export.machine`             programs
==================  =========================================  ===============================

The calibrated URDF's provenance block (what it was fitted from, its verdict) is
:mod:`pipeline.export.provenance`: the choose stage stamps it, the exports read it.

See ``docs/export.md``.
"""

from __future__ import annotations

#: format -> default file suffix
FORMATS = {
    "urdf": ".urdf",
    "ur-calibration": ".yaml",
    "offsets": ".yaml",
    "dh": ".txt",
    "json": ".json",
}
