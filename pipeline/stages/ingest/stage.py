"""Ingest: one streaming pass over a recording -> frames, detections, recording info.

The recording contract is spec/recording.md. The file is read once,
in file order (:func:`pipeline.io.recording.iter_recording`: an MCAP file or a
ROS bag); every image is decoded
and handed to :func:`pipeline.stages.detect.detector.detect_target` in order, on a worker
thread while the records after it are read (:mod:`pipeline.stages.ingest.image_worker`),
so only a few images are in memory at a time. Joint states (small) are kept, and after the
pass every image stamp gets the joint vector interpolated at its
``header.stamp``, a stillness measure and the gap between the bracketing joint
states (:mod:`pipeline.stages.ingest.joints` states the maths). A small crop
around every clean detection is kept too (at most 256 MB): after the pass they
give the sensor's fixed gain pattern, and when there is one, the kept images
are detected again with it divided out (:mod:`pipeline.stages.image.flat_field`).

Outputs: the ``frames`` and ``detections`` artefacts (``schemas/frames.json``,
``schemas/detections.json``; one row per image, ``frame_index`` = the image's
0-based index on its topic in log-time order) and a :class:`RecordingInfo`.

The streaming pass lives in :mod:`pipeline.stages.ingest.stream`, the joint
states' handling (the interpolation and stillness above) in
:mod:`pipeline.stages.ingest.joints`, the settings and :class:`RecordingInfo` in
:mod:`pipeline.stages.ingest.types`; :func:`ingest_recording` strings the steps
together.
"""

from __future__ import annotations

import dataclasses
import math
import os
from typing import Any

import numpy as np
import pandas as pd

from pipeline.errors import BadInput
from pipeline.guardrails.plausibility import joints_outside_chain
from pipeline.io.layout import locate
from pipeline.io.mcap import (
    DEFAULT_IMAGE_TOPICS,
    IMAGE_TYPES,
    StreamState,
    decode_image_message,
    image_to_gray,
)
from pipeline.io.recording import iter_recording, summarize
from pipeline.kinematics.urdf import RobotDescription, chain_joints, parse_urdf
from pipeline.stages.detect.detector import DetectConfig
from pipeline.stages.image.binning import unbin
from pipeline.stages.image.flat_field import CropStore, correct_flat_field
from pipeline.stages.image.image_scale import to_reference
from pipeline.stages.ingest.image_worker import ImageWorker
from pipeline.stages.ingest.joints import (
    arm_joint_names,
    chain_joint_states,
    frame_table,
    other_joints,
)
from pipeline.stages.ingest.stream import (
    RESPONSE_FIT_IMAGES,
    RESPONSE_PROBE_IMAGES,
    Streamed,
    resolve_response,
    take_message,
)
from pipeline.stages.ingest.types import METADATA_KEYS, IngestConfig, Progress, RecordingInfo
from pipeline.stages.response.curve import Response, parse_response

#: the public names of ingest, importable from here (the settings and the recording
#: info live in ingest_types, the streaming pass in ingest_stream, the joint states'
#: handling in ingest_joints)
__all__ = [
    "METADATA_KEYS",
    "RESPONSE_FIT_IMAGES",
    "RESPONSE_PROBE_IMAGES",
    "IngestConfig",
    "Progress",
    "RecordingInfo",
    "infer_links",
    "ingest_recording",
    "load_image",
]


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


#: a joint whose positions span less than this (rad or m) never moves in the recording
STILL_SPAN = 1e-4


def infer_links(
    robot: RobotDescription, joint_names: list[str], span: dict[str, float] | None = None
) -> tuple[str, str, str]:
    """Base and flange link of a URDF: the root link, and the last link the arm's joints move.

    The arm's joints are the actuated joints of ``joint_names`` that move in
    the recording (``span[name] > STILL_SPAN``; all of them when ``span`` is
    None). The last one is the deepest in the tree; the flange is its child
    link, or the child of a fixed joint named like a flange/tool0 hanging from
    it. A joint that never moves (a gripper's fingers, one of them a mimic
    joint) is not the arm's: a link after it is not the flange.

    Returns
    -------
    base, flange : link names
    why : how the flange was chosen (for ``recording.json``'s ``inferred``)
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

    named = [robot.joints[n] for n in joint_names if n in robot.joints]
    arm = named if span is None else [j for j in named if span.get(j.name, 0.0) > STILL_SPAN]
    still = [j.name for j in named if j not in arm]
    arm = arm or named
    if not arm:
        return base, robot.links[-1], f"{robot.links[-1]} (last link of the URDF)"
    last = max(arm, key=lambda j: _depth(j.child))
    tip = last.child
    why = f"child link of {last.name}, the last arm joint"
    if still:
        why += (
            f"; {still} never move in the recording (a gripper's or another device's), "
            "so no link after them is the flange"
        )
    for j in robot.joints.values():
        if j.parent == tip and j.type == "fixed" and j.child.lower() in ("flange", "tool0"):
            return base, j.child, f"{j.child} (fixed to the {why})"
    return base, tip, f"{tip} ({why})"


def ingest_recording(
    path: str | os.PathLike[str],
    config: IngestConfig,
    detect_config: DetectConfig,
    progress: Progress | None = None,
) -> tuple[pd.DataFrame, pd.DataFrame, RecordingInfo]:
    """Stream an MCAP once: decode and detect every image, collect joint states.

    The steps: the detection settings (:func:`_detect_settings`), the streaming pass
    (:func:`pipeline.stages.ingest.stream.take_message`), its checks and warnings
    (:func:`_check_stream`), the chain and its joint states (:func:`_chain`), the
    inferred metadata (:func:`_infer_metadata`), and the two tables (:func:`_tables`).

    Parameters
    ----------
    path : recording (spec/recording.md): an MCAP file or a ROS bag
        (:mod:`pipeline.io.recording`, docs/ros-bags.md)
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
        ``frame_index`` and the keys of :data:`pipeline.stages.detect.detector.RESULT_KEYS`.
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
    polarity, dcfg, resp_fixed, resp_source = _detect_settings(
        path, config, detect_config, metadata
    )
    state = StreamState(path)
    s = Streamed(image_topic=image_topic, dcfg=dcfg, probing=[] if resp_fixed is None else None)
    _stream(path, layout, state, config, s, progress, n_total)
    flat = correct_flat_field(s.crops, s.rows, s.dcfg, (s.height, s.width))
    s.crops = CropStore()  # the crops are done with: free them before the tables
    if progress is not None:
        progress(len(s.rows), n_total)
    # metadata seen while streaming (summary-less files)
    for k2, v2 in [*state.metadata.get("touchup", {}).items(), *s.stream_touchup.items()]:
        metadata.setdefault(k2, v2)
    warnings, urdf = _check_stream(path, state, config, s)
    inferred: dict[str, str] = {}  # inferred metadata keys -> how (for the report)
    chain_names, J_t, Q, implausible = _chain(path, urdf, config, s, metadata, inferred, warnings)
    camera = _infer_metadata(metadata, inferred, s, polarity, resp_fixed, resp_source)
    camera["flat_field"] = flat.summary
    frames, det_df = _tables(s, J_t, Q, chain_names, config, warnings)
    info = RecordingInfo(
        path=path,
        urdf=urdf,
        metadata=metadata,
        inferred=inferred,
        joint_names=chain_names,
        implausible=implausible,
        base_link=metadata["base_link"],
        flange_link=metadata["flange_link"],
        image_topic=str(s.image_topic),
        n_images=len(s.rows),
        n_joint_states=len(J_t),
        truncated=state.truncated,
        warnings=warnings,
        image_width=s.width,
        image_height=s.height,
        camera=camera,
        measurement={
            **state.metadata.get("measurement", {}),
            **summary.metadata.get("measurement", {}),
        },
    )
    return frames, det_df, info


def _stream(
    path: str,
    layout: Any,
    state: StreamState,
    config: IngestConfig,
    s: Streamed,
    progress: Progress | None,
    n_total: int | None,
) -> None:
    """The streaming pass: every message taken into ``s``, images on a second thread in
    order (:class:`~pipeline.stages.ingest.image_worker.ImageWorker`), then the response
    estimated from the images still held back when the file ended."""
    with ImageWorker() as images:
        try:
            for msg in iter_recording(layout, state):
                take_message(path, layout.path, msg, state, config, s, progress, n_total, images)
        except Exception:
            images.drain()  # an image before the failing message failed first: its error
            raise
        images.drain()
    if s.probing is not None:
        got = resolve_response(s.probing, s.rows, s.dcfg, s.crops, final=True, raw=s.probe_raw)
        assert got is not None
        s.dcfg, s.response_est, s.expected = got


def _detect_settings(
    path: str, config: IngestConfig, detect_config: DetectConfig, metadata: dict[str, str]
) -> tuple[str | None, DetectConfig, Response | None, str]:
    """The detection settings of the recording: polarity and camera response.

    Polarity: the detect option, else ``--set`` / the metadata's. Camera response:
    the detect option, else ``--set`` / the metadata's ``camera_response``, else
    estimated from the first images (``auto``: the returned response is None).

    Returns
    -------
    polarity : str or None (automatic)
    dcfg : the DetectConfig images are detected with (its response fixed when known)
    response : the fixed response, or None when it is to be estimated
    source : where the response came from (``option``, ``metadata``)
    """
    polarity = (
        detect_config.polarity or config.overrides.get("polarity") or metadata.get("polarity")
    )
    if polarity and polarity not in ("dark_on_light", "light_on_dark"):
        raise BadInput(
            f"{path}: polarity {polarity!r} (touchup metadata or --set) is not dark_on_light "
            "or light_on_dark"
        )
    dcfg = dataclasses.replace(detect_config, polarity=polarity or None)
    # camera response: the detect option, else --set / metadata camera_response, else estimated
    resp_fixed = dcfg.response
    resp_source = "option"
    if resp_fixed is None:
        resp_text = config.overrides.get("camera_response") or metadata.get(
            "camera_response", "auto"
        )
        resp_source = "metadata"
        try:
            resp_fixed = parse_response(resp_text)
        except ValueError as exc:
            raise BadInput(f"{path}: {exc}") from exc
        dcfg = dataclasses.replace(dcfg, response=resp_fixed)
    return polarity, dcfg, resp_fixed, resp_source


def _check_stream(
    path: str, state: StreamState, config: IngestConfig, s: Streamed
) -> tuple[list[str], str]:
    """The stream's warnings (truncation, damaged chunks, undecodable images, stamp order).

    Returns the warnings and the URDF text. Raises BadInput when there is no URDF, no
    image or no joint state.
    """
    warnings: list[str] = []
    rows, img_log = s.rows, s.img_log
    if state.truncated:
        pct = 100.0 * state.bytes_read / max(state.file_size, 1)
        j_ends = [int(t) for g in s.j_groups.values() for t in g[0].array()[[0, -1]]]
        times = [*img_log[-1:], *j_ends]
        t_first = min([*img_log[:1], *j_ends], default=0)
        span = f", {1e-9 * (max(times) - t_first):.1f} s of data" if times else ""
        warnings.append(
            f"{path}: truncated recording (recorder killed? {state.error}): read "
            f"{state.bytes_read} of {state.file_size} bytes ({pct:.1f} %); the last "
            f"{state.file_size - state.bytes_read} bytes are an incomplete record, anything "
            f"recorded after it is lost; kept {len(rows)} images, {s.n_joint_msgs} joint "
            f"states{span}"
        )
    if s.urdf is None:
        raise BadInput(f"{path}: no URDF on {config.description_topic}")
    if not rows:
        seen = s.seen_image_topics
        extra = f" (image topics present: {sorted(seen)})" if seen else ""
        raise BadInput(f"{path}: no image messages on {s.image_topic or 'any image topic'}{extra}")
    if s.n_joint_msgs == 0:
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
            f"{path}: {n_undecoded} of {len(rows)} images on {s.image_topic} do not decode "
            f"(kept, flagged); first: {first}"
        )
    im_t = np.asarray(s.img_stamp, dtype=np.int64)[np.argsort(np.asarray(img_log), kind="stable")]
    n_back_i = int(np.sum(np.diff(im_t) < 0))
    n_dup_i = int(np.sum(np.diff(np.sort(im_t)) == 0))
    if n_back_i or n_dup_i:
        warnings.append(
            f"{path}: {s.image_topic}: {n_back_i} image stamps go backwards in log-time order "
            f"and {n_dup_i} repeat an earlier stamp"
        )
    return warnings, s.urdf


def _chain(
    path: str,
    urdf: str,
    config: IngestConfig,
    s: Streamed,
    metadata: dict[str, str],
    inferred: dict[str, str],
    warnings: list[str],
) -> tuple[list[str], np.ndarray, np.ndarray, list[str]]:
    """The base-flange chain and its joint states; the chain ends inferred where not given.

    ``metadata`` takes the command-line overrides and the inferred ``base_link`` /
    ``flange_link`` (noted in ``inferred``); ``warnings`` the unknown joint names and
    the joint stamps out of order.

    Returns
    -------
    chain_names : the chain's actuated joints
    J_t, Q : their joint states sorted by stamp (:func:`.ingest_joints.chain_joint_states`)
    implausible : guardrail lines on the joints outside the chain
    """
    robot = _parse(path, urdf)
    seen_names = list(dict.fromkeys(n for key in s.j_groups for n in key))
    j_names = arm_joint_names(path, robot, seen_names, config)
    unknown = [n for n in seen_names if n not in robot.joints]
    if unknown:
        warnings.append(
            f"{path}: {config.joint_topic} also names joints {unknown} that the URDF does "
            "not have (ignored)"
        )
    # metadata: overrides win; inferred keys filled and reported
    metadata.update({k: str(v) for k, v in config.overrides.items() if v is not None})
    spans = {n: _span(v) for n, v in other_joints(s.j_groups, []).items()}
    base_i, flange_i, why = infer_links(robot, j_names, spans)
    if "base_link" not in metadata:
        metadata["base_link"] = base_i
        inferred["base_link"] = f"{base_i} (root link of the URDF)"
    if "flange_link" not in metadata:
        metadata["flange_link"] = flange_i
        inferred["flange_link"] = why
        if "never move" in why:
            warnings.append(f"{path}: no flange_link in the touchup metadata: flange {why}")
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
    J_t, Q, n_back = chain_joint_states(path, s.j_groups, chain_names, config, warnings)
    n_dup = int(np.sum(np.diff(J_t) == 0))
    if n_back or n_dup:
        warnings.append(
            f"{path}: {config.joint_topic}: {n_back} header stamps go backwards and {n_dup} "
            "repeat an earlier stamp (joint states are sorted by stamp)"
        )
    implausible = joints_outside_chain(
        other_joints(s.j_groups, chain_names),
        robot,
        metadata["base_link"],
        metadata["flange_link"],
        over="the recording",
    )
    return chain_names, J_t, Q, implausible


def _span(values: np.ndarray) -> float:
    """How far a joint moves over the recording (inf when a value is not finite: the
    joint stays in the arm, and its bad value is reported with the chain's)."""
    if not values.size or not np.all(np.isfinite(values)):
        return math.inf
    return float(values.max() - values.min())


def _infer_metadata(
    metadata: dict[str, str],
    inferred: dict[str, str],
    s: Streamed,
    polarity: str | None,
    resp_fixed: Response | None,
    resp_source: str,
) -> dict[str, Any]:
    """Fill the polarity, camera response and designated point where the metadata lacks them.

    Each inferred key is noted in ``inferred``. Returns the ``camera`` record of
    :class:`RecordingInfo`.
    """
    if s.bits_note:
        inferred["bit_depth"] = s.bits_note
    if s.bin_note:
        inferred["binning"] = s.bin_note
    if "polarity" not in metadata:
        votes = s.polarity_votes
        n = sum(votes.values())
        best = max(sorted(votes), key=lambda p: votes[p]) if votes else "dark_on_light"
        metadata["polarity"] = polarity or best
        inferred["polarity"] = (
            f"{metadata['polarity']} (automatic per image: {votes.get(best, 0)} of {n} images)"
        )
    camera: dict[str, Any] = {}
    response_est = s.response_est
    if response_est is not None:
        metadata["camera_response"] = response_est.response.spec
        inferred["camera_response"] = response_est.note
        camera = {**response_est.to_dict(), "response_source": "estimated"}
        if response_est.assumed:
            camera["response_source"] = "assumed"
    elif resp_fixed is not None:
        camera = {"response": resp_fixed.spec, "response_source": resp_source}
        metadata["camera_response"] = resp_fixed.spec
        if resp_source == "option":
            inferred["camera_response"] = f"{resp_fixed.spec} (detect option)"
    if "designated_u" not in metadata and s.width:
        metadata["designated_u"] = repr((s.width - 1) / 2.0)
        inferred["designated_u"] = f"{metadata['designated_u']} (image centre)"
    if "designated_v" not in metadata and s.height:
        metadata["designated_v"] = repr((s.height - 1) / 2.0)
        inferred["designated_v"] = f"{metadata['designated_v']} (image centre)"
    return camera


def _tables(
    s: Streamed,
    J_t: np.ndarray,
    Q: np.ndarray,
    chain_names: list[str],
    config: IngestConfig,
    warnings: list[str],
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The ``frames`` and ``detections`` tables, in the images' log-time order."""
    rows = s.rows
    img_log_a = np.asarray(s.img_log, dtype=np.int64)
    order_img = np.argsort(img_log_a, kind="stable")
    stamps = np.asarray(s.img_stamp, dtype=np.int64)[order_img]
    frames = frame_table(stamps, img_log_a[order_img], J_t, Q, chain_names, config)
    ref = (s.height, s.width)
    shapes = s.shapes if len(s.shapes) == len(rows) else [ref] * len(rows)
    det_df = pd.DataFrame([to_reference(unbin(rows[i], s.bin), shapes[i], ref) for i in order_img])
    det_df.insert(0, "frame_index", np.arange(len(rows), dtype=np.int64))
    det_df["reason"] = det_df["reason"].astype(str)
    n_gap = int(frames["joint_gap"].sum())
    if n_gap:
        warnings.append(f"{n_gap} images have a joint-state gap around their stamp")
    return frames, det_df


def _parse(path: str, urdf: str) -> RobotDescription:
    try:
        return parse_urdf(urdf)
    except BadInput as exc:
        raise BadInput(f"{path}: /robot_description: {exc}") from exc
    except Exception as exc:  # noqa: BLE001 - malformed XML etc.
        raise BadInput(f"{path}: /robot_description is not a readable URDF: {exc}") from exc


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
