"""Ingest: one streaming pass over a recording -> frames, detections, recording info.

The recording contract is ../shared/spec/recording.md. The file is read once,
in file order (:func:`pipeline.io_recording.iter_recording`: an MCAP file or a
ROS bag); every image is decoded
and handed to :func:`pipeline.stages.detect.detect_target` at once, so only one
image is in memory at a time. Joint states (small) are kept, and after the
pass every image stamp gets

- the joint vector linearly interpolated at its ``header.stamp``
  (``q(t) = q_k + (t - t_k) / (t_{k+1} - t_k) (q_{k+1} - q_k)`` between the
  bracketing joint states, sorted by their own header stamps);
- a stillness measure: the largest joint speed ``max_j |dq_j/dt|`` over the
  finite differences of consecutive joint states within ``+- still_window_s``
  of the stamp, and the gap between the bracketing joint states.

Outputs: the ``frames`` and ``detections`` artefacts (``schemas/frames.json``,
``schemas/detections.json``; one row per image, ``frame_index`` = the image's
0-based index on its topic in log-time order) and a :class:`RecordingInfo`.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from pipeline.errors import BadInput
from pipeline.io_mcap import (
    DEFAULT_IMAGE_TOPICS,
    IMAGE_TYPES,
    JOINT_TYPES,
    STRING_TYPES,
    StreamState,
    decode_image_message,
    decode_joint_state,
    decode_string,
    image_to_gray,
)
from pipeline.io_recording import TOUCHUP_TOPIC, iter_recording, summarize, touchup_from_message
from pipeline.kinematics.urdf import RobotDescription, chain_joints, parse_urdf
from pipeline.recording_layout import locate
from pipeline.stages.detect import RESULT_KEYS, DetectConfig, detect_target
from pipeline.stages.plausibility import joints_outside_chain
from pipeline.stages.response import parse_response
from pipeline.stages.response_estimate import ResponseEstimate, estimate_response
from pipeline.stages.row_buffer import RowBuffer

#: images held back at the start of a recording to estimate the camera response from
RESPONSE_PROBE_IMAGES = 24
#: of those, how many clean target detections the estimate uses
RESPONSE_FIT_IMAGES = 12

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
        :mod:`pipeline.stages.response`), ``response_source`` (option, metadata,
        estimated), and the estimate's figures (``ResponseEstimate.to_dict``)
    measurement : the recording's ``measurement`` metadata record, when ``vtcal measure``
        wrote it (:mod:`pipeline.measure.summary`: touch-ups planned, converged, given up,
        captures, cell and wall time), as written (strings)
    implausible : guardrail lines on the joint states
        (:func:`pipeline.stages.plausibility.joints_outside_chain`: a joint above the base
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


def _choose_image_topic(
    path: str, topics: dict[str, tuple[str, str]], requested: str | None
) -> str | None:
    """The image topic: the requested one, a spec default, or the only image-typed topic.

    Raises BadInput listing the candidates when there are several and none is a
    spec default (``/camera/image_raw``, ``/camera/image_raw/compressed``).
    """
    if requested:
        return requested
    for t in DEFAULT_IMAGE_TOPICS:
        if t in topics and topics[t][0] in IMAGE_TYPES:
            return t
    imgs = sorted(t for t, (sn, _) in topics.items() if sn in IMAGE_TYPES)
    if len(imgs) > 1:
        raise BadInput(f"{path}: {len(imgs)} image topics {imgs}: choose one with --image-topic")
    return imgs[0] if imgs else None


def infer_links(robot: RobotDescription, joint_names: list[str]) -> tuple[str, str]:
    """Base and flange link of a URDF: the root link, and the child of the last arm joint.

    The last arm joint is the actuated joint of ``joint_names`` deepest in the
    tree; the flange is its child link, or the child of a fixed joint named
    like a flange/tool0 hanging from it.
    """
    children = {j.child for j in robot.joints.values()}
    roots = [ln for ln in robot.links if ln not in children]
    base = roots[0] if roots else robot.links[0]
    depth: dict[str, int] = {}

    def _depth(link: str) -> int:
        if link in depth:
            return depth[link]
        par = [j for j in robot.joints.values() if j.child == link]
        d = 0 if not par else _depth(par[0].parent) + 1
        depth[link] = d
        return d

    arm = [robot.joints[n] for n in joint_names if n in robot.joints]
    if not arm:
        return base, robot.links[-1]
    last = max(arm, key=lambda j: _depth(j.child))
    tip = last.child
    for j in robot.joints.values():
        if j.parent == tip and j.type == "fixed" and j.child.lower() in ("flange", "tool0"):
            return base, j.child
    return base, tip


def ingest_recording(
    path: str | os.PathLike[str],
    config: IngestConfig,
    detect_config: DetectConfig,
    progress: Progress | None = None,
) -> tuple[pd.DataFrame, pd.DataFrame, RecordingInfo]:
    """Stream an MCAP once: decode and detect every image, collect joint states.

    Parameters
    ----------
    path : recording (../shared/spec/recording.md): an MCAP file or a ROS bag
        (:mod:`pipeline.io_recording`, docs/ros-bags.md)
    config : IngestConfig
    detect_config : DetectConfig
        ``polarity`` None takes the metadata's, else automatic per image.
    progress : callable(n_done, n_total or None), optional
        Called every few images with the count so far and the total (from the
        MCAP summary; None when it is missing).

    Returns
    -------
    frames : DataFrame, schema ``frames``
        ``frame_index, stamp_ns, log_time_ns, max_joint_speed, joint_gap_ns,
        nearest_joint_dt_ns, moving, joint_gap, extrapolated`` and one column
        per joint (interpolated position at the stamp).
    detections : DataFrame, schema ``detections``
        ``frame_index`` and the keys of :data:`pipeline.stages.detect.RESULT_KEYS`.
    info : RecordingInfo

    Raises
    ------
    BadInput
        One line naming the file and the topic/value: no images, several image
        topics and none chosen, no joint states, no URDF, unknown image
        encoding, no joint-state name in the URDF (a prefix to strip?), a chain
        joint missing from a message, non-finite joint positions, a bag that
        does not open. Joint-state names the URDF lacks are ignored with a warning.
    """
    path = os.fspath(path)
    layout = locate(path)
    summary = summarize(layout)
    topics = summary.topics
    image_topic = _choose_image_topic(path, topics, config.image_topic)
    n_total: int | None = None
    if topics and image_topic and summary.counts:
        n_total = summary.counts.get(image_topic, 0)
    metadata: dict[str, str] = dict(summary.metadata.get("touchup", {}))
    polarity = (
        detect_config.polarity or config.overrides.get("polarity") or metadata.get("polarity")
    )
    if polarity and polarity not in ("dark_on_light", "light_on_dark"):
        raise BadInput(
            f"{path}: polarity {polarity!r} (touchup metadata or --set) is not dark_on_light "
            "or light_on_dark"
        )
    dcfg = DetectConfig(**{**detect_config.to_dict(), "polarity": polarity or None})
    # camera response: the detect option, else --set / metadata camera_response, else estimated
    resp_text = dcfg.response
    resp_source = "option"
    if resp_text == "auto":
        resp_text = config.overrides.get("camera_response") or metadata.get(
            "camera_response", "auto"
        )
        resp_source = "metadata"
    try:
        resp_fixed = parse_response(resp_text)
    except ValueError as exc:
        raise BadInput(f"{path}: {exc}") from exc
    probing: list[tuple[int, np.ndarray]] | None = None
    response_est: ResponseEstimate | None = None
    if resp_fixed is None:
        probing = []
    else:
        dcfg = DetectConfig(**{**dcfg.to_dict(), "response": resp_fixed.spec})

    state = StreamState(path)
    urdf: str | None = None
    # joint states grouped by their name lists: {names: (stamps, message indices, positions)}
    j_groups: dict[tuple[str, ...], tuple[RowBuffer, RowBuffer, RowBuffer]] = {}
    stream_touchup: dict[str, str] = {}
    rows: list[dict[str, Any]] = []
    img_log: list[int] = []
    img_stamp: list[int] = []
    expected: tuple[float, float, float] | None = None
    width = height = 0
    seen_image_topics: set[str] = set()
    n_joint_msgs = 0
    for msg in iter_recording(layout, state):
        topic, sname, menc = state.topic_type(msg.channel_id)
        if menc != "cdr" and sname.startswith(("sensor_msgs/", "std_msgs/")):
            if topic in (image_topic, config.joint_topic, config.description_topic):
                raise BadInput(
                    f"{path}: topic {topic}: message encoding {menc!r} is not supported for "
                    f"{sname} (ROS 2 messages are read as cdr)"
                )
        if image_topic is None and sname in IMAGE_TYPES:
            image_topic = topic  # no index (truncated file): the first image topic seen
        if topic == image_topic:
            if sname not in IMAGE_TYPES:
                raise BadInput(f"{path}: topic {topic}: type {sname!r} is not an image type")
            k = len(rows)
            try:
                enc = decode_image_message(sname, menc, msg.data)
            except Exception as exc:  # noqa: BLE001 - struct/json/protobuf errors: bad bytes
                raise BadInput(f"{path}: {topic} message {k}: undecodable: {exc}") from exc
            try:
                grey = image_to_gray(enc)
            except ValueError as exc:
                if "unknown" in str(exc):
                    raise BadInput(f"{path}: {topic} message {k}: {exc}") from exc
                det = {kk: v for kk, v in zip(RESULT_KEYS, _nan_row(), strict=True)}
                det["reason"] = f"decode_failed: {exc}"[:120]
                grey = None
            if grey is not None:
                height, width = grey.shape
                if probing is not None:
                    # the response is not known yet: keep the image until it is estimated
                    probing.append((k, np.array(grey, copy=True)))
                    det = {}
                else:
                    det = detect_target(grey, dcfg, expected)
                    if det["found"] and det["quality_ok"]:
                        expected = (det["u"], det["v"], det["s"])
            rows.append(det)
            if probing is not None and len(probing) >= RESPONSE_PROBE_IMAGES:
                dcfg, response_est, expected = _resolve_response(probing, rows, dcfg)
                probing = None
            img_log.append(int(msg.log_time))
            img_stamp.append(int(enc.stamp_ns) if enc.stamp_ns > 0 else int(msg.log_time))
            if progress is not None and (k % 16 == 0):
                progress(k + 1, n_total)
        elif sname in IMAGE_TYPES:
            seen_image_topics.add(topic)
        elif topic == config.joint_topic:
            if sname not in JOINT_TYPES:
                raise BadInput(
                    f"{path}: topic {topic}: type {sname!r} is not sensor_msgs/JointState"
                )
            try:
                stamp, names, pos = decode_joint_state(msg.data)
            except Exception as exc:  # noqa: BLE001 - struct errors etc.: bad bytes
                raise BadInput(
                    f"{path}: {topic} message {n_joint_msgs}: undecodable: {exc}"
                ) from exc
            if len(pos) != len(names):
                raise BadInput(
                    f"{path}: {topic} message {n_joint_msgs}: {len(names)} names but "
                    f"{len(pos)} positions"
                )
            key = _strip_prefix(names, config.joint_prefix)
            group = j_groups.get(key)
            if group is None:  # stamps, message indices, positions: one numpy block each
                group = (RowBuffer(0, np.int64), RowBuffer(0, np.int64), RowBuffer(len(key)))
                j_groups[key] = group
            group[0].append(stamp if stamp > 0 else int(msg.log_time))
            group[1].append(n_joint_msgs)
            group[2].append(pos)
            n_joint_msgs += 1
        elif topic == config.description_topic and urdf is None:
            if sname not in STRING_TYPES:
                raise BadInput(f"{path}: topic {topic}: type {sname!r} is not std_msgs/String")
            urdf = decode_string(msg.data)
        elif topic == TOUCHUP_TOPIC and not stream_touchup and sname in STRING_TYPES:
            stream_touchup = touchup_from_message(layout.path, msg.data)
    if probing is not None:
        dcfg, response_est, expected = _resolve_response(probing, rows, dcfg)
    if progress is not None:
        progress(len(rows), n_total)
    # metadata seen while streaming (summary-less files)
    for k2, v2 in [*state.metadata.get("touchup", {}).items(), *stream_touchup.items()]:
        metadata.setdefault(k2, v2)
    warnings: list[str] = []
    if state.truncated:
        pct = 100.0 * state.bytes_read / max(state.file_size, 1)
        j_ends = [int(t) for g in j_groups.values() for t in g[0].array()[[0, -1]]]
        times = [*img_log[-1:], *j_ends]
        t_first = min([*img_log[:1], *j_ends], default=0)
        span = f", {1e-9 * (max(times) - t_first):.1f} s of data" if times else ""
        warnings.append(
            f"{path}: truncated recording (recorder killed? {state.error}): read "
            f"{state.bytes_read} of {state.file_size} bytes ({pct:.1f} %); the last "
            f"{state.file_size - state.bytes_read} bytes are an incomplete record, anything "
            f"recorded after it is lost; kept {len(rows)} images, {n_joint_msgs} joint "
            f"states{span}"
        )
    if urdf is None:
        raise BadInput(f"{path}: no URDF on {config.description_topic}")
    if not rows:
        extra = f" (image topics present: {sorted(seen_image_topics)})" if seen_image_topics else ""
        raise BadInput(f"{path}: no image messages on {image_topic or 'any image topic'}{extra}")
    if n_joint_msgs == 0:
        raise BadInput(f"{path}: no joint states on {config.joint_topic}")
    if state.bad_chunks:
        warnings.append(
            f"{path}: {len(state.bad_chunks)} chunk(s) failed their CRC or did not decompress "
            f"and were skipped (their messages are lost); first: {state.bad_chunks[0]}"
        )
    if state.orphan_messages:
        warnings.append(
            f"{path}: {state.orphan_messages} messages name a channel whose Channel record is "
            "missing (damaged file) and were skipped"
        )
    n_undecoded = sum(1 for r in rows if str(r.get("reason", "")).startswith("decode_failed"))
    if n_undecoded:
        first = next(r["reason"] for r in rows if str(r["reason"]).startswith("decode_failed"))
        warnings.append(
            f"{path}: {n_undecoded} of {len(rows)} images on {image_topic} do not decode "
            f"(kept, flagged); first: {first}"
        )
    im_t = np.asarray(img_stamp, dtype=np.int64)[np.argsort(np.asarray(img_log), kind="stable")]
    n_back_i = int(np.sum(np.diff(im_t) < 0))
    n_dup_i = int(np.sum(np.diff(np.sort(im_t)) == 0))
    if n_back_i or n_dup_i:
        warnings.append(
            f"{path}: {image_topic}: {n_back_i} image stamps go backwards in log-time order and "
            f"{n_dup_i} repeat an earlier stamp"
        )
    robot = _parse(path, urdf)
    seen_names = list(dict.fromkeys(n for key in j_groups for n in key))
    j_names = _arm_joint_names(path, robot, seen_names, config)
    unknown = [n for n in seen_names if n not in robot.joints]
    if unknown:
        warnings.append(
            f"{path}: {config.joint_topic} also names joints {unknown} that the URDF does "
            "not have (ignored)"
        )
    # metadata: overrides win; inferred keys filled and reported
    metadata.update({k: str(v) for k, v in config.overrides.items() if v is not None})
    inferred: dict[str, str] = {}
    base_i, flange_i = infer_links(robot, j_names)
    if "base_link" not in metadata:
        metadata["base_link"] = base_i
        inferred["base_link"] = f"{base_i} (root link of the URDF)"
    if "flange_link" not in metadata:
        metadata["flange_link"] = flange_i
        inferred["flange_link"] = f"{flange_i} (child link of the last arm joint)"
    for ln in (metadata["base_link"], metadata["flange_link"]):
        if ln not in robot.links:
            raise BadInput(f"{path}: link {ln!r} (touchup metadata/override) is not in the URDF")
    try:
        chain = chain_joints(robot, metadata["base_link"], metadata["flange_link"])
    except BadInput as exc:
        raise BadInput(f"{path}: {exc}") from exc
    chain_names = [j.name for j in chain if j.actuated]
    missing = [n for n in chain_names if n not in j_names]
    if missing:
        raise BadInput(
            f"{path}: {config.joint_topic} lacks URDF chain joints {missing} "
            f"(joint states name {j_names})"
        )
    J_t, Q, n_back = _chain_joint_states(path, j_groups, chain_names, config, warnings)
    n_dup = int(np.sum(np.diff(J_t) == 0))
    if n_back or n_dup:
        warnings.append(
            f"{path}: {config.joint_topic}: {n_back} header stamps go backwards and {n_dup} "
            "repeat an earlier stamp (joint states are sorted by stamp)"
        )
    implausible = joints_outside_chain(
        _other_joints(j_groups, chain_names),
        robot,
        metadata["base_link"],
        metadata["flange_link"],
        over="the recording",
    )
    if "polarity" not in metadata:
        pols = [r for r in rows if r["found"]]
        metadata["polarity"] = polarity or "dark_on_light"
        inferred["polarity"] = f"{metadata['polarity']} (automatic, from {len(pols)} images)"
    camera: dict[str, Any] = {}
    if response_est is not None:
        metadata["camera_response"] = response_est.response.spec
        inferred["camera_response"] = response_est.note
        camera = {**response_est.to_dict(), "response_source": "estimated"}
        if response_est.note.startswith("linear (assumed"):
            camera["response_source"] = "assumed"
    elif resp_fixed is not None:
        camera = {"response": resp_fixed.spec, "response_source": resp_source}
        metadata["camera_response"] = resp_fixed.spec
        if resp_source == "option":
            inferred["camera_response"] = f"{resp_fixed.spec} (detect option)"
    if "designated_u" not in metadata and width:
        metadata["designated_u"] = repr((width - 1) / 2.0)
        inferred["designated_u"] = f"{metadata['designated_u']} (image centre)"
    if "designated_v" not in metadata and height:
        metadata["designated_v"] = repr((height - 1) / 2.0)
        inferred["designated_v"] = f"{metadata['designated_v']} (image centre)"

    # frame table, log-time order
    img_log_a = np.asarray(img_log, dtype=np.int64)
    order_img = np.argsort(img_log_a, kind="stable")
    stamps = np.asarray(img_stamp, dtype=np.int64)[order_img]
    frames = _frame_table(stamps, img_log_a[order_img], J_t, Q, chain_names, config)
    det_df = pd.DataFrame([rows[i] for i in order_img])
    det_df.insert(0, "frame_index", np.arange(len(rows), dtype=np.int64))
    det_df["reason"] = det_df["reason"].astype(str)
    n_gap = int(frames["joint_gap"].sum())
    if n_gap:
        warnings.append(f"{n_gap} images have a joint-state gap around their stamp")
    info = RecordingInfo(
        path=path,
        urdf=urdf,
        metadata=metadata,
        inferred=inferred,
        joint_names=chain_names,
        implausible=implausible,
        base_link=metadata["base_link"],
        flange_link=metadata["flange_link"],
        image_topic=str(image_topic),
        n_images=len(rows),
        n_joint_states=len(J_t),
        truncated=state.truncated,
        warnings=warnings,
        image_width=width,
        image_height=height,
        camera=camera,
        measurement={
            **state.metadata.get("measurement", {}),
            **summary.metadata.get("measurement", {}),
        },
    )
    return frames, det_df, info


def _resolve_response(
    probing: list[tuple[int, np.ndarray]], rows: list[dict[str, Any]], dcfg: DetectConfig
) -> tuple[DetectConfig, ResponseEstimate, tuple[float, float, float] | None]:
    """Estimate the camera response from the held-back images, then detect them with it.

    ``rows[k]`` of every held-back image ``k`` is filled in place, in order, each
    capture's detection steering the next one's (``expected``) as in the stream.
    """
    est = estimate_response((g for _, g in probing), dcfg, max_images=RESPONSE_FIT_IMAGES)
    cfg = DetectConfig(**{**dcfg.to_dict(), "response": est.response.spec})
    expected: tuple[float, float, float] | None = None
    for k, grey in probing:
        det = detect_target(grey, cfg, expected)
        if det["found"] and det["quality_ok"]:
            expected = (det["u"], det["v"], det["s"])
        rows[k] = det
    probing.clear()
    return cfg, est, expected


def _nan_row() -> list[Any]:
    from pipeline.stages.detect import empty_result

    d = empty_result("")
    return [d[k] for k in RESULT_KEYS]


def _parse(path: str, urdf: str) -> RobotDescription:
    try:
        return parse_urdf(urdf)
    except BadInput as exc:
        raise BadInput(f"{path}: /robot_description: {exc}") from exc
    except Exception as exc:  # noqa: BLE001 - malformed XML etc.
        raise BadInput(f"{path}: /robot_description is not a readable URDF: {exc}") from exc


def _strip_prefix(names: list[str], prefix: str) -> tuple[str, ...]:
    """Joint-state names without ``prefix`` (``robot1/joint_1 -> joint_1``); others as they are."""
    if not prefix:
        return tuple(names)
    k = len(prefix)
    return tuple(n[k:] if n.startswith(prefix) else n for n in names)


def _arm_joint_names(
    path: str, robot: RobotDescription, names: list[str], config: IngestConfig
) -> list[str]:
    """The joint-state names that are actuated URDF joints (in the order first seen).

    Names the URDF does not have (a gripper's fingers, another robot's joints)
    are left to the caller to note. Raises BadInput when no name is an actuated
    URDF joint (wrong URDF, or a name prefix that ``--joint-prefix`` should strip).
    """
    act = [n for n, j in robot.joints.items() if j.actuated]
    arm = [n for n in names if n in act]
    if arm:
        return arm
    hint = ""
    prefixes = {n[: n.rfind("/") + 1] for n in names if "/" in n}
    if len(prefixes) == 1 and not config.joint_prefix:
        hint = f"; the names carry the prefix {prefixes.pop()!r}: give it with --joint-prefix"
    raise BadInput(
        f"{path}: {config.joint_topic} names joints {names} that the URDF on "
        f"{config.description_topic} does not have (URDF joints: {sorted(act)}){hint}"
    )


def _other_joints(
    groups: dict[tuple[str, ...], tuple[RowBuffer, RowBuffer, RowBuffer]],
    chain_names: list[str],
) -> dict[str, np.ndarray]:
    """Every joint-state value of the joints outside the chain, by joint name (for the guardrails)."""
    out: dict[str, list[np.ndarray]] = {}
    for key, (_ts, _ks, ps) in groups.items():
        arr = ps.array()
        for k, name in enumerate(key):
            if name not in chain_names:
                out.setdefault(name, []).append(arr[:, k])
    return {n: np.concatenate(v) for n, v in out.items()}


def _chain_joint_states(
    path: str,
    groups: dict[tuple[str, ...], tuple[RowBuffer, RowBuffer, RowBuffer]],
    chain_names: list[str],
    config: IngestConfig,
    warnings: list[str],
) -> tuple[np.ndarray, np.ndarray, int]:
    """The chain's joint positions from joint-state messages of any name order.

    Each message's positions are picked by name (``q_j = position[name.index(j)]``),
    so joint order and extra joints do not matter. Messages naming none of the
    chain joints (a gripper published on the same topic) are skipped and noted
    in ``warnings``.

    Returns
    -------
    J_t : (m,) int64, the stamps sorted (stable)
    Q : (m, n) float64, the chain joints at ``J_t`` (columns in ``chain_names`` order)
    n_back : how many stamps go backwards in message order

    Raises
    ------
    BadInput
        A message naming some but not all chain joints; a non-finite chain joint position.
    """
    idx: list[np.ndarray] = []
    stamps: list[np.ndarray] = []
    rows: list[np.ndarray] = []
    skipped = 0
    for key, buffers in groups.items():
        ts, ks, ps = (b.array() for b in buffers)
        have = [n for n in chain_names if n in key]
        if not have:
            skipped += len(ts)
            continue
        if len(have) < len(chain_names):
            missing = [n for n in chain_names if n not in key]
            raise BadInput(
                f"{path}: {config.joint_topic} message {ks[0]}: joints {missing} missing "
                f"(has {list(key)})"
            )
        cols = np.array([key.index(n) for n in chain_names])
        q = np.asarray(ps)[:, cols]
        bad = np.flatnonzero(~np.all(np.isfinite(q), axis=1))
        if bad.size:
            raise BadInput(
                f"{path}: {config.joint_topic} message {ks[bad[0]]}: non-finite position "
                f"{q[bad[0]]}"
            )
        idx.append(np.asarray(ks))
        stamps.append(np.asarray(ts, dtype=np.int64))
        rows.append(q)
    if skipped:
        warnings.append(
            f"{path}: {config.joint_topic}: {skipped} messages name none of the chain joints "
            f"{chain_names} (another device's joint states) and were skipped"
        )
    if not rows:
        raise BadInput(f"{path}: no joint states of the chain joints {chain_names}")
    k_all = np.concatenate(idx)
    t_all = np.concatenate(stamps)
    q_all = np.concatenate(rows)
    in_order = np.argsort(k_all, kind="stable")
    n_back = int(np.sum(np.diff(t_all[in_order]) < 0))
    if len(t_all) < 2:
        raise BadInput(
            f"{path}: only one joint state on {config.joint_topic}: at least two are needed to "
            "interpolate the joints at the image stamps"
        )
    o = in_order[np.argsort(t_all[in_order], kind="stable")]
    return t_all[o], q_all[o], n_back


def _frame_table(
    stamps: np.ndarray,
    log_times: np.ndarray,
    J_t: np.ndarray,
    Q: np.ndarray,
    names: list[str],
    config: IngestConfig,
) -> pd.DataFrame:
    """Joint vector and stillness at every image stamp (see module docstring)."""
    n = len(stamps)
    tq = (J_t - J_t[0]).astype(np.float64) * 1e-9
    ts = (stamps - J_t[0]).astype(np.float64) * 1e-9
    q_at = np.empty((n, Q.shape[1]))
    for j in range(Q.shape[1]):
        q_at[:, j] = np.interp(ts, tq, Q[:, j])
    k = np.searchsorted(J_t, stamps, side="right")  # J_t[k-1] <= t < J_t[k]
    before = np.clip(k - 1, 0, len(J_t) - 1)
    after = np.clip(k, 0, len(J_t) - 1)
    extrap = (k == 0) | (k == len(J_t))
    gap = np.where(extrap, -1, J_t[after] - J_t[before])
    near = np.minimum(np.abs(stamps - J_t[before]), np.abs(J_t[after] - stamps))
    # joint speed of consecutive states
    if len(J_t) > 1:
        dt = np.diff(tq)
        dq = np.abs(np.diff(Q, axis=0))
        spd = np.max(dq, axis=1) / np.where(dt > 0, dt, np.inf)
        tmid = 0.5 * (tq[1:] + tq[:-1])
    else:
        spd = np.zeros(0)
        tmid = np.zeros(0)
    w = config.still_window_s
    lo = np.searchsorted(tmid, ts - w, side="left")
    hi = np.searchsorted(tmid, ts + w, side="right")
    max_speed = np.array(
        [float(spd[a:b].max()) if b > a else np.nan for a, b in zip(lo, hi, strict=True)]
    )
    # no difference inside the window (gap): use the bracketing pair
    nan = ~np.isfinite(max_speed)
    if nan.any() and len(spd):
        max_speed[nan] = spd[np.clip(k[nan] - 1, 0, len(spd) - 1)]
    df = pd.DataFrame(
        {
            "frame_index": np.arange(n, dtype=np.int64),
            "stamp_ns": stamps.astype(np.int64),
            "log_time_ns": log_times.astype(np.int64),
            "max_joint_speed": max_speed,
            "joint_gap_ns": gap.astype(np.int64),
            "nearest_joint_dt_ns": near.astype(np.int64),
            "moving": max_speed > config.moving_speed_rad_s,
            "joint_gap": (gap > config.max_joint_gap_s * 1e9) | extrap,
            "extrapolated": extrap,
        }
    )
    for j, nm in enumerate(names):
        df[nm] = q_at[:, j]
    return df


def load_image(path: str | os.PathLike[str], image_topic: str, frame_index: int) -> np.ndarray:
    """Decode one image again: the ``frame_index``-th message (log-time order) of a topic.

    Returns the grey image ``(H, W)``. Raises BadInput when there is no such frame.
    """
    path = os.fspath(path)
    layout = locate(path)
    try:
        if layout.kind != "mcap":
            raise LookupError("not one MCAP file: stream it")
        from mcap.reader import make_reader

        with open(path, "rb") as f:
            r = make_reader(f)
            if r.get_summary() is not None:
                for i, (sc, ch, m) in enumerate(
                    r.iter_messages(topics=[image_topic], log_time_order=True)
                ):
                    if i == frame_index:
                        enc = decode_image_message(
                            sc.name if sc else "", ch.message_encoding, m.data
                        )
                        return image_to_gray(enc)
                raise BadInput(f"{path}: {image_topic} has no frame {frame_index}")
    except BadInput:
        raise
    except Exception:  # noqa: BLE001 - fall back to a linear scan
        pass
    state = StreamState(path)
    i = 0
    for msg in iter_recording(layout, state):
        topic, sname, menc = state.topic_type(msg.channel_id)
        if topic != image_topic:
            continue
        if i == frame_index:
            return image_to_gray(decode_image_message(sname, menc, msg.data))
        i += 1
    raise BadInput(f"{path}: {image_topic} has no frame {frame_index}")
