"""rosbag2 sqlite3 (``.db3``) and ROS 1 (``.bag``) recordings, read with ``rosbags``.

The container formats are read by the `rosbags <https://gitlab.com/ternaris/rosbags>`_
package (pure Python), not by vtcal. Messages come out in the shape
:mod:`pipeline.io.mcap`'s decoders read, so ingest sees one kind of stream:

- rosbag2 ``.db3``: messages are ROS 2 CDR already and pass through unchanged.
- ROS 1 ``.bag``: messages are ROS 1 serialised. The types vtcal reads
  (``sensor_msgs/Image``, ``sensor_msgs/CompressedImage``,
  ``sensor_msgs/JointState``, ``std_msgs/String``) are deserialised with the
  ROS 1 (Noetic) type store and serialised again as ROS 2 (Humble) CDR, field
  by field (the only layout difference of these types is ROS 1's
  ``Header.seq``, which ROS 2 dropped). Other types are passed on undecoded
  with message encoding ``ros1``; ingest never reads them.

Each connection becomes an MCAP-style :class:`mcap.records.Channel` and
:class:`mcap.records.Schema` in the :class:`~pipeline.io.mcap.StreamState`
(schema name = the ROS 2 style type name ``pkg/msg/Type``, which rosbags uses
for both ROS versions), and each message an MCAP :class:`mcap.records.Message`
whose ``log_time`` is the bag's receive time.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from mcap.records import Channel, Message, Schema

from pipeline.errors import BadInput
from pipeline.io.mcap import IMAGE_TYPES, JOINT_TYPES, STRING_TYPES, StreamState

#: message types converted from ROS 1 to ROS 2 CDR (the ones ingest decodes)
DECODED_TYPES = frozenset(t for t in (*IMAGE_TYPES, *JOINT_TYPES, *STRING_TYPES) if "/msg/" in t)


def _rosbags() -> Any:
    """The ``rosbags`` package (a runtime dependency; a clear error if it is missing)."""
    try:
        import rosbags.rosbag1
        import rosbags.rosbag2
        import rosbags.typesys
    except ImportError as exc:  # pragma: no cover - a broken install
        raise BadInput(
            "reading .db3 and ROS 1 .bag recordings needs the rosbags package "
            "(pip install 'rosbags>=0.11,<0.12')"
        ) from exc
    return rosbags


def open_reader(path: Path) -> Any:
    """A rosbags reader for a ``.db3`` file / rosbag2 directory or a ROS 1 ``.bag`` (opened).

    Raises
    ------
    BadInput
        One line naming the file and rosbags' own complaint.
    """
    rb = _rosbags()
    try:
        if path.suffix == ".bag":
            reader = rb.rosbag1.Reader(path)
        else:
            reader = rb.rosbag2.Reader(path)
        reader.open()
    except Exception as exc:  # noqa: BLE001 - ReaderError, sqlite errors, OSError, ...
        raise BadInput(f"{path}: not a readable ROS bag: {exc}".rstrip()) from exc
    return reader


def summary(path: Path) -> tuple[dict[str, tuple[str, str]], dict[str, int]]:
    """``({topic: (type, encoding)}, {topic: message count})`` from the bag's index."""
    reader = open_reader(path)
    try:
        topics: dict[str, tuple[str, str]] = {}
        counts: dict[str, int] = {}
        for c in reader.connections:
            topics[c.topic] = (c.msgtype, "cdr")
            counts[c.topic] = counts.get(c.topic, 0) + int(c.msgcount)
        return topics, counts
    finally:
        reader.close()


def first_message(path: Path, topic: str) -> bytes | None:
    """CDR bytes of the first message on ``topic`` (None when the topic is absent)."""
    reader = open_reader(path)
    try:
        conns = [c for c in reader.connections if c.topic == topic]
        if not conns:
            return None
        conv = _Converter(path.suffix == ".bag")
        for conn, _, raw in reader.messages(connections=conns):
            return conv.cdr(raw, conn.msgtype)[0]
        return None
    finally:
        reader.close()


def iter_bag_messages(path: Path, state: StreamState) -> Iterator[Message]:
    """Every message of a rosbags-readable bag, in the bag's time order, filling ``state``.

    ``state.file_size`` and ``state.bytes_read`` are the bag's total size (the
    reader checks the bag's index, so a bag that opens is read whole).
    """
    reader = open_reader(path)
    files = [f for f in path.iterdir() if f.name != "metadata.yaml"] if path.is_dir() else [path]
    state.file_size = sum(os.path.getsize(f) for f in files)
    conv = _Converter(path.suffix == ".bag")
    try:
        for c in reader.connections:
            enc = "cdr" if (c.msgtype in DECODED_TYPES or not conv.ros1) else "ros1"
            state.schemas[c.id] = Schema(id=c.id, name=c.msgtype, encoding="ros2msg", data=b"")
            state.channels[c.id] = Channel(
                id=c.id, topic=c.topic, message_encoding=enc, schema_id=c.id, metadata={}
            )
        for seq, (conn, t, raw) in enumerate(reader.messages()):
            data, _ = conv.cdr(raw, conn.msgtype)
            yield Message(
                channel_id=conn.id, sequence=seq, log_time=int(t), publish_time=int(t), data=data
            )
    except BadInput:
        raise
    except Exception as exc:  # noqa: BLE001 - a damaged bag: keep what was read
        state.truncated = True
        state.error = f"{type(exc).__name__}: {exc}"[:200]
    finally:
        reader.close()
    if not state.truncated:
        state.bytes_read = state.file_size


class _Converter:
    """ROS 1 serialised -> ROS 2 CDR for :data:`DECODED_TYPES`; CDR passes through."""

    def __init__(self, ros1: bool) -> None:
        self.ros1 = ros1
        if ros1:
            ts = _rosbags().typesys
            self.src = ts.get_typestore(ts.Stores.ROS1_NOETIC)
            self.dst = ts.get_typestore(ts.Stores.ROS2_HUMBLE)

    def cdr(self, raw: bytes | memoryview, msgtype: str) -> tuple[bytes, bool]:
        """``(bytes, converted)``: CDR of a ROS 1 message of a decoded type, else ``raw``."""
        if not self.ros1 or msgtype not in DECODED_TYPES:
            return bytes(raw), False
        msg = self.src.deserialize_ros1(raw, msgtype)
        return bytes(self.dst.serialize_cdr(self._to_ros2(msg), msgtype)), True

    def _to_ros2(self, msg: Any) -> Any:
        """The same message as an instance of the ROS 2 type (fields ROS 2 lacks dropped)."""
        cls = self.dst.types[msg.__msgtype__]
        kw = {}
        for f in dataclasses.fields(cls):
            if f.name.startswith("__"):
                continue
            v = getattr(msg, f.name)
            kw[f.name] = self._to_ros2(v) if hasattr(v, "__msgtype__") else v
        return cls(**kw)
