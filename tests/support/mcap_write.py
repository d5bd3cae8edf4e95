"""A tiny ROS 2 recording writer for ingest tests and benchmarks.

Writes what spec/recording.md describes (URDF, joint states, images,
``touchup`` metadata) with :mod:`mcap_ros2.writer`, with knobs to produce the
bad inputs ingest must reject (no images, unknown encodings, ...). The schema
texts name nested definitions ``MSG: pkg/Type`` (``short_names=True``) or
``MSG: pkg/msg/Type`` (as rosbag2 does) so readers are exercised on both.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from typing import Any

import cv2
import numpy as np
from mcap.writer import CompressionType
from mcap_ros2.writer import Writer

_SEP = "=" * 80

_TIME = "int32 sec\nuint32 nanosec\n"
_HEADER = "builtin_interfaces{m}Time stamp\nstring frame_id\n"
_DEFS = {
    "std_msgs/msg/String": "string data\n",
    "sensor_msgs/msg/JointState": (
        "std_msgs{m}Header header\n\nstring[] name\nfloat64[] position\n"
        "float64[] velocity\nfloat64[] effort\n"
    ),
    "sensor_msgs/msg/Image": (
        "# a comment, as rosbag2 writes them\nstd_msgs{m}Header header\nuint32 height\n"
        "uint32 width\nstring encoding\nuint8 is_bigendian\nuint32 step\nuint8[] data\n"
    ),
    "sensor_msgs/msg/CompressedImage": "std_msgs{m}Header header\nstring format\nuint8[] data\n",
}


def msgdef(datatype: str, short_names: bool) -> str:
    """Schema text of ``datatype`` with its nested Header/Time definitions."""
    m = "/" if short_names else "/msg/"
    text = _DEFS[datatype].replace("{m}", "/")  # field types: always pkg/Type
    if "Header" in text:
        text += f"{_SEP}\nMSG: std_msgs{m}Header\n" + _HEADER.replace("{m}", "/")
        text += f"{_SEP}\nMSG: builtin_interfaces{m}Time\n" + _TIME
    return text


def _stamp(ns: int) -> dict[str, int]:
    return {"sec": int(ns // 1_000_000_000), "nanosec": int(ns % 1_000_000_000)}


def write_recording(
    path: str | os.PathLike[str],
    *,
    urdf: str | None,
    joint_names: Sequence[str],
    joints: Iterable[tuple[int, np.ndarray]],
    images: Iterable[tuple[int, np.ndarray]],
    encoding: str = "mono8",
    image_topic: str | None = None,
    metadata: dict[str, str] | None = None,
    short_names: bool = False,
    compression: CompressionType = CompressionType.ZSTD,
    image_latency_ns: int = 30_000_000,
    chunk_size: int = 1 << 20,
    foxglove: str | None = None,
) -> None:
    """Write a recording; messages are interleaved in log-time order.

    Parameters
    ----------
    urdf : URDF text for ``/robot_description`` (None: leave it out)
    joint_names : names written in every JointState
    joints : ``(stamp_ns, q)`` joint states (log time = stamp + 2 ms)
    images : ``(stamp_ns, grey uint8/uint16 image)``; log time = stamp + latency
    encoding : ``mono8``, ``mono16``, ``rgb8``, ``bgr8`` (raw Image), ``png`` or
        ``jpeg`` (CompressedImage), or any other string (written raw as is,
        for the unknown-encoding test)
    image_topic : default ``/camera/image_raw`` (raw) or ``.../compressed``
    foxglove : None (ROS 2 images), ``"json"`` or ``"protobuf"``: images as
        ``foxglove.RawImage`` (``mono8``) / ``foxglove.CompressedImage`` (``png``)
        in that encoding (the schema data is a stub: vtcal does not read it)
    """
    compressed = encoding in ("png", "jpeg")
    topic = image_topic or ("/camera/image_raw/compressed" if compressed else "/camera/image_raw")
    events: list[tuple[int, int, str, tuple[int, Any]]] = []
    for t, q in joints:
        events.append((int(t) + 2_000_000, 1, "js", (int(t), np.asarray(q, dtype=float))))
    for t, img in images:
        events.append((int(t) + image_latency_ns, 2, "img", (int(t), img)))
    events.sort(key=lambda e: (e[0], e[1]))
    with open(path, "wb") as f:
        w = Writer(f, chunk_size=chunk_size, compression=compression)
        s_str = w.register_msgdef("std_msgs/msg/String", msgdef("std_msgs/msg/String", short_names))
        s_js = w.register_msgdef(
            "sensor_msgs/msg/JointState", msgdef("sensor_msgs/msg/JointState", short_names)
        )
        img_type = "sensor_msgs/msg/CompressedImage" if compressed else "sensor_msgs/msg/Image"
        s_img = w.register_msgdef(img_type, msgdef(img_type, short_names))
        fox_channel = None
        if foxglove is not None:
            fox_type = "foxglove.CompressedImage" if compressed else "foxglove.RawImage"
            mw = w._writer  # the underlying mcap writer: a channel in another encoding
            sid = mw.register_schema(
                name=fox_type,
                encoding="jsonschema" if foxglove == "json" else "protobuf",
                data=b"{}" if foxglove == "json" else b"",
            )
            fox_channel = mw.register_channel(topic=topic, message_encoding=foxglove, schema_id=sid)
        t0 = events[0][0] - 1_000_000 if events else 0
        if urdf is not None:
            w.write_message(
                "/robot_description", s_str, {"data": urdf}, log_time=t0, publish_time=t0
            )
        for seq, (log_t, _, kind, payload) in enumerate(events):
            t, data = payload
            msg: dict[str, Any]
            if kind == "js":
                msg = {
                    "header": {"stamp": _stamp(t), "frame_id": ""},
                    "name": list(joint_names),
                    "position": [float(x) for x in data],
                    "velocity": [],
                    "effort": [],
                }
                w.write_message(
                    "/joint_states", s_js, msg, log_time=log_t, publish_time=log_t, sequence=seq
                )
                continue
            img = np.asarray(data)
            if fox_channel is not None:
                payload_b = _foxglove_payload(t, img, encoding, str(foxglove))
                w._writer.add_message(
                    channel_id=fox_channel,
                    log_time=log_t,
                    publish_time=log_t,
                    data=payload_b,
                    sequence=seq,
                )
                continue
            header = {"stamp": _stamp(t), "frame_id": "camera"}
            if compressed:
                ok, buf = cv2.imencode(".png" if encoding == "png" else ".jpg", img)
                assert ok
                msg = {"header": header, "format": encoding, "data": buf.tobytes()}
            else:
                if encoding in ("rgb8", "bgr8"):
                    px = np.repeat(img[:, :, None], 3, axis=2).astype(np.uint8)
                    step = img.shape[1] * 3
                elif encoding == "mono16":
                    px = img.astype("<u2")
                    step = img.shape[1] * 2
                else:
                    px = img.astype(np.uint8)
                    step = img.shape[1]
                msg = {
                    "header": header,
                    "height": img.shape[0],
                    "width": img.shape[1],
                    "encoding": encoding,
                    "is_bigendian": 0,
                    "step": step,
                    "data": px.tobytes(),
                }
            w.write_message(topic, s_img, msg, log_time=log_t, publish_time=log_t, sequence=seq)
        if metadata is not None:
            w.add_metadata("touchup", dict(metadata))
        w.finish()


def _foxglove_payload(t: int, img: np.ndarray, encoding: str, enc: str) -> bytes:
    """A foxglove RawImage (mono8) or CompressedImage (png/jpeg) message, JSON or protobuf."""
    compressed = encoding in ("png", "jpeg")
    if compressed:
        ok, buf = cv2.imencode(".png" if encoding == "png" else ".jpg", img)
        assert ok
        data = buf.tobytes()
    else:
        data = np.ascontiguousarray(img.astype(np.uint8)).tobytes()
    sec, nsec = int(t // 1_000_000_000), int(t % 1_000_000_000)
    if enc == "json":
        import base64
        import json

        obj: dict[str, Any] = {
            "timestamp": {"sec": sec, "nsec": nsec},
            "frame_id": "camera",
            "data": base64.b64encode(data).decode(),
        }
        if compressed:
            obj["format"] = encoding
        else:
            obj.update(width=img.shape[1], height=img.shape[0], encoding="mono8", step=img.shape[1])
        return json.dumps(obj).encode()
    if compressed:
        from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

        m = CompressedImage(frame_id="camera", data=data, format=encoding)
    else:
        from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

        m = RawImage(
            frame_id="camera",
            width=img.shape[1],
            height=img.shape[0],
            encoding="mono8",
            step=img.shape[1],
            data=data,
        )
    m.timestamp.seconds = sec
    m.timestamp.nanos = nsec
    out: bytes = m.SerializeToString()
    return out
