"""Ingest's settings and what it learns about a recording (:mod:`pipeline.stages.ingest.stage`).

:class:`IngestConfig` (the stage's options), :class:`RecordingInfo` (what
ingest learnt besides the per-image tables: ``recording.json``), the spec's
``touchup`` metadata keys, and the progress callback's type. Importable from
:mod:`pipeline.stages.ingest.stage` too.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

Progress = Callable[[int, "int | None"], None]

#: ``touchup`` metadata keys of the spec
METADATA_KEYS = (
    "base_link",
    "flange_link",
    "target_diameter_m",
    "designated_u",
    "designated_v",
    "designated_size_px",
    "threshold_px",
    "threshold_size_px",
    "polarity",
    "known_distances",
    "camera_response",
)

#: further ``touchup`` keys of the spec that vtcal reads (the verdict's tolerance, the
#: robot's stable name, the cell's target names)
OTHER_METADATA_KEYS = ("tolerance_mm", "robot_id", "target_order")


@dataclass
class IngestConfig:
    """Ingest settings.

    Attributes
    ----------
    image_topic : str or None
        None: automatic (``/camera/image_raw``, ``/camera/image_raw/compressed``,
        else the only image-typed topic, Foxglove types included).
    joint_topic, description_topic : str
    joint_prefix : str
        Stripped from the start of joint-state names before they are matched
        with the URDF's (``robot1/`` makes ``robot1/joint_1`` ``joint_1``).
    overrides : dict
        Command-line values of the ``touchup`` metadata keys (win over the file).
    still_window_s : float
        Half-width of the window around an image stamp for the joint speed.
    moving_speed_rad_s : float
        Joint speed above which a capture counts as taken while moving.
    max_joint_gap_s : float
        Bracketing joint states farther apart than this flag a joint-state gap.
    """

    image_topic: str | None = None
    joint_topic: str = "/joint_states"
    description_topic: str = "/robot_description"
    joint_prefix: str = ""
    overrides: dict[str, str] = field(default_factory=dict)
    still_window_s: float = 0.06
    moving_speed_rad_s: float = 2e-3
    max_joint_gap_s: float = 0.1


@dataclass
class RecordingInfo:
    """What ingest learnt about a recording (besides the per-image tables).

    Attributes
    ----------
    path : the recording
    urdf : URDF text from the description topic (the nominal robot)
    metadata : the ``touchup`` keys after command-line overrides, inferred keys filled
    inferred : key -> how it was inferred (for the report)
    joint_names : actuated joints of the base-flange chain (the frames' joint columns)
    base_link, flange_link : chain ends
    image_topic : topic the images were read from
    n_images, n_joint_states : messages read
    truncated : the file ended early (recorder killed)
    warnings : one line each (truncation, joint-state gaps)
    image_width, image_height : size of the images (px)
    camera : what was found about the camera: ``response`` (the curve detection used,
        :mod:`pipeline.stages.response.curve`), ``response_source`` (option, metadata,
        estimated), and the estimate's figures (``ResponseEstimate.to_dict``)
    measurement : the recording's ``measurement`` metadata record, when ``vtcal measure``
        wrote it (:mod:`pipeline.live.summary`: touch-ups planned, converged, given up,
        captures, cell and wall time), as written (strings)
    implausible : guardrail lines on the joint states
        (:func:`pipeline.guardrails.plausibility.joints_outside_chain`: a joint above the base
        or after the flange link that moves); the run refuses them before extraction
    """

    path: str
    urdf: str
    metadata: dict[str, str]
    inferred: dict[str, str]
    joint_names: list[str]
    base_link: str
    flange_link: str
    image_topic: str
    n_images: int
    n_joint_states: int
    truncated: bool
    warnings: list[str]
    image_width: int = 0
    image_height: int = 0
    camera: dict[str, Any] = field(default_factory=dict)
    implausible: list[str] = field(default_factory=list)
    measurement: dict[str, str] = field(default_factory=dict)
