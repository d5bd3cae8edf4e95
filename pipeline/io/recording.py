"""A recording, whatever container ROS wrote it in: one MCAP file or a bag.

vtcal reads (see docs/ros-bags.md):

- ``mcap``: one MCAP file (spec/recording.md), streamed by
  :mod:`pipeline.io.mcap`;
- ``rosbag2-mcap``: a rosbag2 bag directory (``metadata.yaml`` and one or more
  split ``.mcap`` files), each file streamed by :mod:`pipeline.io.mcap` in the
  order ``metadata.yaml`` lists them, as one recording;
- ``rosbag2-sqlite3``: a rosbag2 directory of ``.db3`` files, or one ``.db3``
  file, read by :mod:`pipeline.io.rosbags`;
- ``ros1``: a ROS 1 ``.bag`` file, read by :mod:`pipeline.io.rosbags`;
- a compressed rosbag2 directory of either storage (``ros2 bag record
  --compression-mode file|message --compression-format zstd``: ``NAME.mcap.zstd``
  files, or zstd-compressed message bytes), read by :mod:`pipeline.io.rosbags`,
  which decompresses.

Every kind yields MCAP-style records into one
:class:`~pipeline.io.mcap.StreamState`, with ROS 2 CDR message bytes for the
types ingest decodes, so ingest and the report's image loader do not care
which container it was.

The ``touchup`` metadata of the spec is an MCAP metadata record, which a bag
written by ``ros2 bag record`` or ``rosbag record`` cannot hold; it may come
instead as the first ``std_msgs/String`` message on :data:`TOUCHUP_TOPIC`
holding a JSON object of the same keys (an MCAP metadata record, where there
is one, wins key by key; ``--set`` wins over both).
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from mcap.records import Channel, Message, Schema

from pipeline.errors import BadInput
from pipeline.io.layout import Layout
from pipeline.io.mcap import StreamState, decode_string, iter_messages

#: topic carrying the ``touchup`` metadata as a JSON object in a ``std_msgs/String``
TOUCHUP_TOPIC = "/touchup/metadata"


@dataclass
class Summary:
    """What a recording's index says, before streaming it (empty when it has none).

    Attributes
    ----------
    topics : ``{topic: (type name, message encoding)}``
    counts : ``{topic: message count}`` (may be empty)
    metadata : ``{record name: {key: value}}``; ``touchup`` includes the keys of
        :data:`TOUCHUP_TOPIC` that no metadata record sets
    """

    topics: dict[str, tuple[str, str]] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)


def parse_touchup_json(text: str) -> dict[str, str]:
    """The ``touchup`` keys of a :data:`TOUCHUP_TOPIC` message (values as strings).

    Raises ``ValueError`` when the text is not a JSON object.
    """
    obj = json.loads(text)
    if not isinstance(obj, dict):
        raise ValueError(f"expected a JSON object of touchup keys, got {type(obj).__name__}")
    return {str(k): v if isinstance(v, str) else json.dumps(v) for k, v in obj.items()}


def summarize(layout: Layout) -> Summary:
    """Topics, message counts and metadata from the index (no message streaming).

    A file whose index is missing or broken (a truncated MCAP) gives an empty
    or partial summary; streaming it still works. A :data:`TOUCHUP_TOPIC`
    message that is not a JSON object raises :class:`BadInput`.
    """
    s = Summary()
    topic_meta: bytes | None = None
    if not layout.read_by_rosbags:
        for f in layout.files:
            part, first = _mcap_summary(f)
            for t, tv in part.topics.items():
                s.topics.setdefault(t, tv)
            for t, n in part.counts.items():
                s.counts[t] = s.counts.get(t, 0) + n
            for name, kv in part.metadata.items():
                s.metadata.setdefault(name, {}).update(kv)
            if topic_meta is None:
                topic_meta = first
    else:
        from pipeline.io import rosbags as io_rosbags

        s.topics, s.counts = io_rosbags.summary(layout.path)
        if TOUCHUP_TOPIC in s.topics:
            topic_meta = io_rosbags.first_message(layout.path, TOUCHUP_TOPIC)
    if topic_meta is not None:
        touchup = s.metadata.setdefault("touchup", {})
        for k, v in touchup_from_message(layout.path, topic_meta).items():
            touchup.setdefault(k, v)
    return s


def touchup_from_message(path: Path, data: bytes) -> dict[str, str]:
    """``touchup`` keys of one :data:`TOUCHUP_TOPIC` message (CDR ``std_msgs/String``).

    Raises BadInput naming the recording, the topic and the text.
    """
    try:
        text = decode_string(data)
    except ValueError as exc:
        raise BadInput(f"{path}: {TOUCHUP_TOPIC}: undecodable: {exc}") from exc
    try:
        return parse_touchup_json(text)
    except ValueError as exc:
        raise BadInput(
            f"{path}: {TOUCHUP_TOPIC}: not a JSON object of touchup keys ({exc}): {text[:80]!r}"
        ) from exc


def _mcap_summary(path: Path) -> tuple[Summary, bytes | None]:
    """Summary of one MCAP file and its first :data:`TOUCHUP_TOPIC` message, if any."""
    from mcap.reader import make_reader

    s = Summary()
    first: bytes | None = None
    try:
        with open(path, "rb") as f:
            r = make_reader(f)
            summ = r.get_summary()
            if summ is None:
                return s, None
            for ch in summ.channels.values():
                sc = summ.schemas.get(ch.schema_id)
                s.topics[ch.topic] = (sc.name if sc else "", ch.message_encoding)
            if summ.statistics is not None:
                for cid, n in summ.statistics.channel_message_counts.items():
                    cch = summ.channels.get(cid)
                    if cch is not None:
                        s.counts[cch.topic] = s.counts.get(cch.topic, 0) + int(n)
            for m in r.iter_metadata():
                s.metadata[m.name] = dict(m.metadata)
            if TOUCHUP_TOPIC in s.topics:
                for _, _, msg in r.iter_messages(topics=[TOUCHUP_TOPIC]):
                    first = bytes(msg.data)
                    break
    except Exception:  # noqa: BLE001 - a broken summary just means: stream
        return Summary(), None
    return s, first


def iter_recording(layout: Layout, state: StreamState) -> Iterator[Message]:
    """Every message of the recording, file after file, filling ``state``.

    Split MCAP files each have their own channel ids; they are mapped to one
    id per ``(topic, schema name, encoding)`` in ``state``. Sizes, skipped
    chunks and orphan messages add up over the files; a file that ends early
    sets ``state.truncated`` (its ``error`` names the file) and the next
    files are still read.

    Raises
    ------
    BadInput
        A file that is missing or not an MCAP file at all; a bag rosbags cannot open.
    """
    if layout.read_by_rosbags:
        from pipeline.io import rosbags as io_rosbags

        yield from io_rosbags.iter_bag_messages(layout.path, state)
        return
    if layout.kind == "mcap":
        yield from iter_messages(layout.files[0], state)
        return
    ids: dict[tuple[str, str, str], int] = {}
    for f in layout.files:
        sub = StreamState(str(f))
        local: dict[int, int] = {}
        for msg in iter_messages(f, sub):
            gid = local.get(msg.channel_id)
            if gid is None:
                topic, sname, menc = sub.topic_type(msg.channel_id)
                key = (topic, sname, menc)
                gid = ids.setdefault(key, len(ids) + 1)
                if gid not in state.channels:
                    ch = sub.channels[msg.channel_id]
                    sc = sub.schemas.get(ch.schema_id)
                    if sc is not None:
                        state.schemas[gid] = Schema(
                            id=gid, name=sc.name, encoding=sc.encoding, data=sc.data
                        )
                    state.channels[gid] = Channel(
                        id=gid,
                        topic=topic,
                        message_encoding=menc,
                        schema_id=gid if sc is not None else 0,
                        metadata=dict(ch.metadata),
                    )
                local[msg.channel_id] = gid
            yield Message(
                channel_id=gid,
                sequence=msg.sequence,
                log_time=msg.log_time,
                publish_time=msg.publish_time,
                data=msg.data,
            )
        state.file_size += sub.file_size
        state.bytes_read += sub.bytes_read
        state.bad_chunks += [f"{f.name}: {b}" for b in sub.bad_chunks]
        state.orphan_messages += sub.orphan_messages
        for name, kv in sub.metadata.items():
            state.metadata.setdefault(name, {}).update(kv)
        if sub.truncated and not state.truncated:
            state.truncated = True
            state.error = f"{f.name}: {sub.error}"
