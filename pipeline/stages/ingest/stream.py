"""Ingest's streaming pass: every message of a recording once, in file order.

:func:`take_message` takes one message into a :class:`Streamed`: an image is
decoded and handed to :func:`pipeline.stages.detect.detector.detect_target` (at once, or
in order on the worker thread of :mod:`pipeline.stages.ingest.image_worker`: either way
only a few images are in memory at a time), each clean detection steering the
next one's (``expected``); the first :data:`RESPONSE_PROBE_IMAGES` images are
held back when the camera response is to be estimated, and detected once it
is (:func:`resolve_response`). Joint states (small) are kept grouped by their
name lists (:mod:`pipeline.stages.ingest.joints`); the URDF and the touch-up
metadata are taken from their topics.
"""

from __future__ import annotations

import dataclasses
from concurrent.futures import Future
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from mcap.records import Message

from pipeline.errors import BadInput
from pipeline.io.mcap import (
    IMAGE_TYPES,
    JOINT_TYPES,
    STRING_TYPES,
    StreamState,
    decode_joint_state,
    decode_string,
    significant_bits,
    to_full_range,
)
from pipeline.io.recording import TOUCHUP_TOPIC, touchup_from_message
from pipeline.kinematics.urdf import urdf_text
from pipeline.stages.detect.blob import image_polarity
from pipeline.stages.detect.detector import RESULT_KEYS, DetectConfig, detect_target, empty_result
from pipeline.stages.image.binning import bin_image, choose_binning, scaled_position
from pipeline.stages.image.flat_field import CropStore
from pipeline.stages.image.response_estimate import ResponseEstimate, estimate_response
from pipeline.stages.ingest.image_worker import ImageWorker
from pipeline.stages.ingest.joints import JointGroups, strip_prefix
from pipeline.stages.ingest.prefetch import Decoded, decode_image
from pipeline.stages.ingest.row_buffer import RowBuffer
from pipeline.stages.ingest.types import IngestConfig, Progress

#: images held back at the start of a recording to estimate the camera response from
RESPONSE_PROBE_IMAGES = 24
#: ... and, while those show too few clean targets to estimate from (a lamp or a plate
#: edge spoiling the first target's captures), up to this many in steps of the above
RESPONSE_PROBE_MAX = 96
#: of those, how many clean target detections the estimate uses
RESPONSE_FIT_IMAGES = 12


@dataclass
class Streamed:
    """What the streaming pass collected (filled in message order by :func:`take_message`).

    Attributes
    ----------
    image_topic : the image topic (the first image-typed topic seen when there was no index)
    dcfg : the detection settings (the estimated response filled in once known)
    probing : images held back until the response is estimated, ``(row, grey)``; None
        once it is known
    response_est : the response estimate, when there was one
    urdf : the first description message
    j_groups : joint states by name list (:data:`pipeline.stages.ingest.joints.JointGroups`)
    stream_touchup : ``touchup`` metadata from the touch-up topic
    rows : one detection dict per image, in message order
    img_log, img_stamp : each image's log time and header stamp (ns)
    expected : the last clean detection's ``(u, v, s)``, steering the next
    width, height : image size (px)
    seen_image_topics : other image-typed topics (for the "no images" message)
    n_joint_msgs : joint-state messages read
    crops : crops of the clean detections, for the sensor's gain pattern
        (:mod:`pipeline.stages.image.flat_field`)
    bits, bits_note : the sample depth of 16-bit images (0: none seen), inferred from
        the first one's largest value (:func:`pipeline.io.mcap.significant_bits`), and
        how it was inferred
    shapes : each image's ``(H, W)`` as decoded ((0, 0) when it was not): detections are in
        that image's pixels until :func:`pipeline.stages.image.image_scale.to_reference`
        maps them to the largest size's (level-of-detail images)
    bin, bin_note : the binning factor images are detected at (0: no image yet; detections
        in ``rows`` are in binned pixels until :func:`pipeline.stages.image.binning.unbin`) and why
    polarity_votes : without a declared polarity, how many images automatic detection read
        as each polarity (:func:`pipeline.stages.detect.blob.image_polarity`)
    probe_raw : the held-back images' raw-grey detections the response estimate made, in
        ``probing`` order (a retry with more images held back does not redo them)
    """

    image_topic: str | None
    dcfg: DetectConfig
    probing: list[tuple[int, np.ndarray]] | None
    response_est: ResponseEstimate | None = None
    urdf: str | None = None
    j_groups: JointGroups = field(default_factory=dict)
    stream_touchup: dict[str, str] = field(default_factory=dict)
    rows: list[dict[str, Any]] = field(default_factory=list)
    img_log: list[int] = field(default_factory=list)
    img_stamp: list[int] = field(default_factory=list)
    expected: tuple[float, float, float] | None = None
    width: int = 0
    height: int = 0
    seen_image_topics: set[str] = field(default_factory=set)
    n_joint_msgs: int = 0
    crops: CropStore = field(default_factory=CropStore)
    bits: int = 0
    bits_note: str = ""
    bin: int = 0
    bin_note: str = ""
    polarity_votes: dict[str, int] = field(default_factory=dict)
    shapes: list[tuple[int, int]] = field(default_factory=list)
    probe_raw: list[dict[str, Any]] = field(default_factory=list)


def take_message(
    path: str,
    layout_path: Path,
    msg: Message,
    state: StreamState,
    config: IngestConfig,
    s: Streamed,
    progress: Progress | None,
    n_total: int | None,
    images: ImageWorker | None = None,
) -> None:
    """One message of the stream: an image, a joint state, the URDF or touch-up metadata.

    ``images``: the worker that takes the images, in order, while the stream is read
    (:mod:`pipeline.stages.ingest.image_worker`), each image's decoding started at
    once on its decoding thread; None: decoded and taken here.
    """
    topic, sname, menc = state.topic_type(msg.channel_id)
    if menc != "cdr" and sname.startswith(("sensor_msgs/", "std_msgs/")):
        if topic in (s.image_topic, config.joint_topic, config.description_topic):
            raise BadInput(
                f"{path}: topic {topic}: message encoding {menc!r} is not supported for "
                f"{sname} (ROS 2 messages are read as cdr)"
            )
    if s.image_topic is None and sname in IMAGE_TYPES:
        s.image_topic = topic  # no index (truncated file): the first image topic seen
    if topic == s.image_topic:
        if images is None:
            _take_image(path, topic, sname, menc, msg, s, progress, n_total)
        else:
            pre = images.decode(decode_image, sname, menc, msg.data)
            images.submit(_take_image, path, topic, sname, menc, msg, s, progress, n_total, pre)
    elif sname in IMAGE_TYPES:
        s.seen_image_topics.add(topic)
    elif topic == config.joint_topic:
        _take_joint_state(path, topic, sname, msg, config, s)
    elif topic == config.description_topic and s.urdf is None:
        if sname not in STRING_TYPES:
            raise BadInput(f"{path}: topic {topic}: type {sname!r} is not std_msgs/String")
        try:
            s.urdf = urdf_text(decode_string(msg.data))
        except ValueError as exc:
            raise BadInput(f"{path}: {topic}: undecodable: {exc}") from exc
    elif topic == TOUCHUP_TOPIC and not s.stream_touchup and sname in STRING_TYPES:
        s.stream_touchup = touchup_from_message(layout_path, msg.data)


def _take_image(
    path: str,
    topic: str,
    sname: str,
    menc: str,
    msg: Message,
    s: Streamed,
    progress: Progress | None,
    n_total: int | None,
    pre: Future[Decoded] | None = None,
) -> None:
    """Decode and detect one image (or hold it back until the response is estimated)."""
    if sname not in IMAGE_TYPES:
        raise BadInput(f"{path}: topic {topic}: type {sname!r} is not an image type")
    k = len(s.rows)
    # decoded ahead, or being decoded: its result; not started yet (the other core was
    # busy): taken back and decoded here rather than waiting for the thread's turn
    if pre is not None and (pre.done() or not pre.cancel()):
        enc_, grey, enc_exc, grey_exc = pre.result()
    else:
        enc_, grey, enc_exc, grey_exc = decode_image(sname, menc, msg.data)
    if enc_exc is not None or enc_ is None:
        raise BadInput(f"{path}: {topic} message {k}: undecodable: {enc_exc}") from enc_exc
    enc = enc_
    if grey_exc is not None:
        exc = grey_exc
        if "unknown" in str(exc):
            raise BadInput(f"{path}: {topic} message {k}: {exc}") from exc
        det = {kk: v for kk, v in zip(RESULT_KEYS, _nan_row(), strict=True)}
        det["reason"] = f"decode_failed: {exc}"[:120]
        grey = None
        s.shapes.append((0, 0))
    if grey is not None and grey.dtype == np.uint16:
        grey = _full_range(grey, k, s)
    if grey is not None:
        shape = (int(grey.shape[0]), int(grey.shape[1]))
        last = next((sh for sh in reversed(s.shapes) if sh[0] > 0), shape)
        if shape != last and s.expected is not None:  # a level-of-detail image: rescale
            f = shape[1] / last[1]
            u, v, sz = s.expected
            s.expected = (scaled_position(u, f), scaled_position(v, f), f * sz)
        s.shapes.append(shape)
        if shape[0] * shape[1] > s.height * s.width:  # the reference: the largest size
            s.height, s.width = shape
        if s.bin == 0:  # decided once, on the first image (pipeline.stages.image.binning)
            s.bin, s.bin_note = choose_binning(grey, s.dcfg)
        grey = bin_image(grey, s.bin)
        if s.dcfg.polarity is None:  # automatic per image: the recording's, by majority
            pol = image_polarity(grey, s.dcfg.downsample, s.dcfg.compiled)
            s.polarity_votes[pol] = s.polarity_votes.get(pol, 0) + 1
        if s.probing is not None:
            # the response is not known yet: keep the image until it is estimated
            s.probing.append((k, np.array(grey, copy=True)))
            det = {}
        else:
            det = detect_target(grey, s.dcfg, s.expected)
            if det["found"] and det["quality_ok"]:
                s.expected = (det["u"], det["v"], det["s"])
                if shape == (s.height, s.width):  # the sensor's gain: its own pixels only
                    s.crops.add(k, grey, det)
    s.rows.append(det)
    n_held = len(s.probing) if s.probing is not None else 0
    if n_held >= RESPONSE_PROBE_IMAGES and n_held % RESPONSE_PROBE_IMAGES == 0:
        assert s.probing is not None
        got = resolve_response(
            s.probing, s.rows, s.dcfg, s.crops, final=n_held >= RESPONSE_PROBE_MAX, raw=s.probe_raw
        )
        if got is not None:
            s.dcfg, s.response_est, s.expected = got
            s.probing = None
    s.img_log.append(int(msg.log_time))
    s.img_stamp.append(int(enc.stamp_ns) if enc.stamp_ns > 0 else int(msg.log_time))
    if progress is not None and (k % 16 == 0):
        progress(k + 1, n_total)


def _full_range(grey: np.ndarray, k: int, s: Streamed) -> np.ndarray:
    """A 16-bit image stretched to the full range of the depth its data use.

    The depth is inferred once, from the first 16-bit image; an image whose
    values exceed it raises it (noted) for the rest of the recording.
    """
    bits = significant_bits(grey)
    if bits > s.bits:
        top = int(grey.max())
        if s.bits == 0:
            s.bits_note = f"{bits} (16-bit images whose first one's largest value is {top}"
            s.bits_note += ")" if bits == 16 else ": scaled to the 16-bit range)"
        else:
            s.bits_note += f"; raised to {bits} at image {k} (largest value {top})"
        s.bits = bits
    return to_full_range(grey, s.bits)


def _take_joint_state(
    path: str, topic: str, sname: str, msg: Message, config: IngestConfig, s: Streamed
) -> None:
    """Keep one joint-state message in its name list's group."""
    if sname not in JOINT_TYPES:
        raise BadInput(f"{path}: topic {topic}: type {sname!r} is not sensor_msgs/JointState")
    try:
        stamp, names, pos = decode_joint_state(msg.data)
    except Exception as exc:  # noqa: BLE001 - struct errors etc.: bad bytes
        raise BadInput(f"{path}: {topic} message {s.n_joint_msgs}: undecodable: {exc}") from exc
    if len(pos) != len(names):
        raise BadInput(
            f"{path}: {topic} message {s.n_joint_msgs}: {len(names)} names but {len(pos)} positions"
        )
    key = strip_prefix(names, config.joint_prefix)
    group = s.j_groups.get(key)
    if group is None:  # stamps, message indices, positions: one numpy block each
        group = (RowBuffer(0, np.int64), RowBuffer(0, np.int64), RowBuffer(len(key)))
        s.j_groups[key] = group
    group[0].append(stamp if stamp > 0 else int(msg.log_time))
    group[1].append(s.n_joint_msgs)
    group[2].append(pos)
    s.n_joint_msgs += 1


def resolve_response(
    probing: list[tuple[int, np.ndarray]],
    rows: list[dict[str, Any]],
    dcfg: DetectConfig,
    crops: CropStore | None = None,
    final: bool = True,
    raw: list[dict[str, Any]] | None = None,
) -> tuple[DetectConfig, ResponseEstimate, tuple[float, float, float] | None] | None:
    """Estimate the camera response from the held-back images, then detect them with it.

    ``rows[k]`` of every held-back image ``k`` is filled in place, in order, each
    capture's detection steering the next one's (``expected``) as in the stream;
    clean ones are kept in ``crops`` as the stream keeps its own. Unless ``final``,
    None (nothing done: hold more images back) when fewer than half of
    :data:`RESPONSE_FIT_IMAGES` of them showed a clean target edge. ``raw`` keeps the
    estimate's raw-grey detections between the calls (none is made twice).
    """
    est = estimate_response(
        (g for _, g in probing), dcfg, max_images=RESPONSE_FIT_IMAGES, detections=raw
    )
    if not final and est.n_images < RESPONSE_FIT_IMAGES // 2:
        return None
    cfg = dataclasses.replace(dcfg, response=est.response)
    expected: tuple[float, float, float] | None = None
    for k, grey in probing:
        det = detect_target(grey, cfg, expected)
        if det["found"] and det["quality_ok"]:
            expected = (det["u"], det["v"], det["s"])
            if crops is not None:
                crops.add(k, grey, det)
        rows[k] = det
    probing.clear()
    return cfg, est, expected


def _nan_row() -> list[Any]:
    d = empty_result("")
    return [d[k] for k in RESULT_KEYS]
