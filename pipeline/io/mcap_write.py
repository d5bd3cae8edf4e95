"""Streaming MCAP writer (ROS 2 profile, CDR, ros2msg schemas): the simulator's and ``vtcal measure``'s.

Messages are queued by log time in a small heap and written once the
simulated clock has passed their log time, so the file is in log-time order
while memory stays bounded (only messages of the last few tens of
milliseconds are held). The ROS 2 message definitions are the files in
``schemas/ros2/<pkg>/msg/<Type>.msg``; nested definitions are appended after
a line of 80 ``=`` and ``MSG: pkg/Type`` as rosbag2 does.
"""

from __future__ import annotations

import heapq
import re
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

from mcap.writer import CompressionType
from mcap_ros2.writer import Writer

from pipeline.io import resources

MSG_DIR = resources.SCHEMA_DIR / "ros2"
_BUILTIN = {
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
    "int32", "uint32", "int64", "uint64", "string", "wstring",
}  # fmt: skip


def _msg_path(pkg_type: str) -> Path:
    pkg, _, name = pkg_type.replace("/msg/", "/").partition("/")
    return MSG_DIR / pkg / "msg" / f"{name}.msg"


def msgdef(datatype: str) -> str:
    """Full ``ros2msg`` schema text of ``pkg/msg/Type`` with its nested definitions.

    Nested types are found depth-first in field order and each listed once.
    """
    top = _msg_path(datatype).read_text()
    seen: list[str] = []

    def walk(text: str) -> None:
        for line in text.splitlines():
            line = line.split("#", 1)[0].strip()
            if not line:
                continue
            ftype = re.sub(r"\[.*\]$", "", line.split()[0])
            if ftype in _BUILTIN or "=" in line.split()[-1]:
                continue
            if "/" not in ftype:
                continue
            if ftype not in seen:
                seen.append(ftype)
                walk(_msg_path(ftype).read_text())

    walk(top)
    parts = [top.rstrip("\n")]
    for t in seen:
        parts.append("=" * 80 + f"\nMSG: {t}\n" + _msg_path(t).read_text().rstrip("\n"))
    return "\n".join(parts) + "\n"


def stamp(ns: int) -> dict[str, int]:
    """``builtin_interfaces/Time`` of a nanosecond time."""
    return {"sec": int(ns // 1_000_000_000), "nanosec": int(ns % 1_000_000_000)}


class Recorder:
    """Write ROS 2 messages to an MCAP stream in log-time order.

    Parameters
    ----------
    f : binary file object
    chunk_size : int
        Bytes per zstd chunk.
    """

    TYPES = (
        "std_msgs/msg/String",
        "sensor_msgs/msg/JointState",
        "sensor_msgs/msg/Image",
        "sensor_msgs/msg/CompressedImage",
    )

    def __init__(self, f: IO[bytes], chunk_size: int = 4 * 1024 * 1024) -> None:
        self._f = f
        self._w = Writer(f, chunk_size=chunk_size, compression=CompressionType.ZSTD)
        self._schemas: dict[str, Any] = {}
        self._heap: list[tuple[int, int, str, str, Any, Callable[[int, int], None] | None]] = []
        self._order = 0
        self.sequence = 0
        self.counts: dict[str, int] = {}
        self.last_log_time: dict[str, int] = {}

    def _schema(self, datatype: str) -> Any:
        if datatype not in self._schemas:
            self._schemas[datatype] = self._w.register_msgdef(datatype, msgdef(datatype))
        return self._schemas[datatype]

    def metadata(self, name: str, data: dict[str, str]) -> None:
        self._w.add_metadata(name, data)

    def push(
        self,
        log_time_ns: int,
        topic: str,
        datatype: str,
        msg: dict[str, Any],
        on_write: Callable[[int, int], None] | None = None,
    ) -> None:
        """Queue a message; ``on_write(index_on_topic, sequence)`` runs when it is written."""
        heapq.heappush(self._heap, (int(log_time_ns), self._order, topic, datatype, msg, on_write))
        self._order += 1

    def flush(self, until_ns: int | None = None) -> None:
        """Write every queued message with log time ``<= until_ns`` (all if None)."""
        while self._heap and (until_ns is None or self._heap[0][0] <= until_ns):
            t, _, topic, datatype, msg, cb = heapq.heappop(self._heap)
            self._w.write_message(
                topic,
                self._schema(datatype),
                msg,
                log_time=t,
                publish_time=t,
                sequence=self.sequence,
            )
            idx = self.counts.get(topic, 0)
            if cb is not None:
                cb(idx, self.sequence)
            self.counts[topic] = idx + 1
            self.last_log_time[topic] = t
            self.sequence += 1

    def cut_chunk(self) -> int:
        """Write everything queued, close the chunk in progress; return the file position."""
        self.flush(None)
        inner = getattr(self._w, "_writer", None)
        if inner is not None:
            inner.flush()
        return int(self._f.tell())

    def finish(self) -> None:
        self.flush(None)
        self._w.finish()


class NullRecorder(Recorder):
    """A recorder that keeps nothing: a simulated cell run standalone (behind an adapter
    server, whose client writes the recording) streams its messages nowhere."""

    def __init__(self) -> None:  # no file, no writer
        self.sequence = 0
        self.counts = {}
        self.last_log_time = {}

    def metadata(self, name: str, data: dict[str, str]) -> None:
        return None

    def push(
        self,
        log_time_ns: int,
        topic: str,
        datatype: str,
        msg: dict[str, Any],
        on_write: Callable[[int, int], None] | None = None,
    ) -> None:
        return None

    def flush(self, until_ns: int | None = None) -> None:
        return None

    def cut_chunk(self) -> int:
        return 0

    def finish(self) -> None:
        return None
