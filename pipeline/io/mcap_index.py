"""A few messages of one topic read through an MCAP file's index (no pass over the file).

The report shows a few dozen camera images of a recording of tens of
thousands of messages. :func:`topic_messages` finds them from the summary
section an MCAP writer appends (``ChunkIndex`` records) and the ``MessageIndex``
records after each chunk, then reads and decompresses only the chunks that
hold them, each only as far as its last wanted record (a zstd chunk is
decompressed from its start; nothing after the last wanted record is).

Messages are numbered as ingest numbers them (:mod:`pipeline.stages.ingest.stage`):
the 0-based rank of a message among the topic's messages in log-time order,
ties kept in file order (a stable sort of the file-order sequence). File order
is the order of the files, of the chunks in a file (``chunk_start_offset``) and
of the records in a chunk (their offset), so the rank is the position in the
sort by ``(log_time, file, chunk offset, record offset)``; chunks that overlap
in time or records out of log-time order inside a chunk are ranked right.

The index cannot say which chunks a streaming pass would have skipped (a
failed CRC, a chunk that does not decompress) or which messages it would have
dropped (no Channel record): the caller passes the number of messages the
topic had when the recording was ingested, and the index is used only when it
counts the same. Anything the index does not hold or does not agree with
(no summary, a chunk without message indexes, messages outside chunks, a count
or a record that does not match) gives None: the caller streams the file.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterable, Sequence
from contextlib import ExitStack
from dataclasses import dataclass
from typing import IO

from mcap.reader import SeekingReader
from mcap.records import ChunkIndex

#: record opcodes of the MCAP format
MESSAGE_OPCODE = 0x05
MESSAGE_INDEX_OPCODE = 0x07
CHUNK_OPCODE = 0x06
#: opcode (1) and record length (8)
RECORD_HEAD = struct.Struct("<BQ")
#: a Message record's fixed fields: channel id, sequence, log time, publish time
MESSAGE_HEAD = struct.Struct("<HIQQ")


@dataclass(frozen=True)
class TopicMessage:
    """One message found through the index.

    Attributes
    ----------
    schema_name, message_encoding : of its channel
    log_time : ns
    data : the message bytes
    """

    schema_name: str
    message_encoding: str
    log_time: int
    data: bytes


@dataclass(frozen=True)
class _Entry:
    """Where one message of the topic is: its sort key, its chunk and where its record ends."""

    key: tuple[int, int, int, int]  # log time, file, chunk offset, record offset
    chunk: ChunkIndex
    #: the offset of the next indexed record of the chunk (any channel), else the chunk's size
    end: int


def topic_messages(
    files: Sequence[str | os.PathLike[str]],
    topic: str,
    ranks: Iterable[int],
    expected_count: int,
) -> dict[int, TopicMessage] | None:
    """The messages of ``topic`` of the wanted ranks, ``{rank: message}``, or None.

    Parameters
    ----------
    files : the recording's MCAP files, in reading order (one, or a bag's split files)
    topic : the topic (every channel of it counts)
    ranks : wanted 0-based ranks in log-time order (see the module docstring);
        ranks past the end are left out of the result
    expected_count : how many messages the topic had when it was ingested

    Returns
    -------
    dict or None
        None when the index cannot be trusted to number the messages as a
        streaming pass does (see the module docstring); the caller streams.
    """
    want = sorted({int(r) for r in ranks if int(r) >= 0})
    try:
        with ExitStack() as stack:
            handles: list[IO[bytes]] = []
            entries: list[_Entry] = []
            names: list[dict[int, tuple[str, str]]] = []
            for i, path in enumerate(files):
                handles.append(stack.enter_context(open(path, "rb")))
                found = _file_entries(handles[-1], i, topic)
                if found is None:
                    return None
                entries += found[0]
                names.append(found[1])
            if len(entries) != expected_count:
                return None
            entries.sort(key=lambda e: e.key)
            picked = {r: entries[r] for r in want if r < len(entries)}
            return _read_picked(handles, picked, names)
    except Exception:  # noqa: BLE001 - an index that does not read is no index: stream
        return None


def _file_entries(
    fh: IO[bytes], file_no: int, topic: str
) -> tuple[list[_Entry], dict[int, tuple[str, str]]] | None:
    """The index entries of ``topic`` in one file, and its channels' (schema, encoding).

    None when the file has no usable index: no summary or statistics, no chunk
    index, or index entries that do not add up to the statistics' message
    count (messages outside chunks, chunks written without message indexes).
    """
    summary = SeekingReader(fh).get_summary()
    if summary is None or not summary.chunk_indexes or summary.statistics is None:
        return None
    channels = {}
    for cid, ch in summary.channels.items():
        if ch.topic == topic:
            sc = summary.schemas.get(ch.schema_id)
            channels[cid] = (sc.name if sc is not None else "", ch.message_encoding)
    counts = summary.statistics.channel_message_counts
    out: list[_Entry] = []
    for ci in summary.chunk_indexes:
        if not channels.keys() & ci.message_index_offsets.keys():
            continue
        index = _chunk_message_indexes(fh, ci)
        starts = sorted(off for entries in index.values() for _, off in entries)
        ends = dict(zip(starts, [*starts[1:], ci.uncompressed_size], strict=True))
        for cid in channels.keys() & index.keys():
            for log_time, off in index[cid]:
                out.append(_Entry((log_time, file_no, ci.chunk_start_offset, off), ci, ends[off]))
    if len(out) != sum(int(counts.get(cid, 0)) for cid in channels):
        return None
    return out, channels


def _chunk_message_indexes(fh: IO[bytes], ci: ChunkIndex) -> dict[int, list[tuple[int, int]]]:
    """``{channel id: [(log time, record offset in the chunk)]}`` of one chunk.

    The chunk's MessageIndex records follow it, ``message_index_length`` bytes
    from the first one: read at once.
    """
    first = min(ci.message_index_offsets.values())
    fh.seek(first)
    raw = fh.read(ci.message_index_length)
    if len(raw) != ci.message_index_length:
        raise ValueError(f"message indexes at byte {first} run past the end of the file")
    out: dict[int, list[tuple[int, int]]] = {}
    pos = 0
    while pos < len(raw):
        op, length = RECORD_HEAD.unpack_from(raw, pos)
        pos += RECORD_HEAD.size
        if op == MESSAGE_INDEX_OPCODE:
            cid, n = struct.unpack_from("<HI", raw, pos)
            if 6 + n > length or n % 16:
                raise ValueError(f"MessageIndex at byte {first + pos}: {n} bytes of entries")
            pairs = struct.unpack_from(f"<{n // 8}Q", raw, pos + 6)
            out[cid] = list(zip(pairs[0::2], pairs[1::2], strict=True))
        pos += length
    if out.keys() != ci.message_index_offsets.keys():
        raise ValueError(f"message indexes at byte {first} do not match the chunk index")
    return out


def _read_picked(
    handles: Sequence[IO[bytes]],
    picked: dict[int, _Entry],
    names: Sequence[dict[int, tuple[str, str]]],
) -> dict[int, TopicMessage]:
    """Read the picked messages, each chunk once and only up to its last picked record."""
    by_chunk: dict[tuple[int, int], list[int]] = {}
    for r, e in picked.items():
        by_chunk.setdefault((e.key[1], e.key[2]), []).append(r)
    out: dict[int, TopicMessage] = {}
    for (file_no, _), rs in sorted(by_chunk.items()):
        ci = picked[rs[0]].chunk
        body = _chunk_prefix(handles[file_no], ci, max(picked[r].end for r in rs))
        for r in rs:
            off = picked[r].key[3]
            cid, log_time, data = _message_at(body, off)
            if cid not in names[file_no] or log_time != picked[r].key[0]:
                raise ValueError(f"chunk at byte {ci.chunk_start_offset}: record {off} mismatch")
            schema, enc = names[file_no][cid]
            out[r] = TopicMessage(schema, enc, log_time, data)
    return out


def _chunk_prefix(fh: IO[bytes], ci: ChunkIndex, end: int) -> bytes:
    """The first ``end`` bytes of the chunk's decompressed records (all of them if shorter)."""
    fh.seek(ci.chunk_start_offset)
    raw = fh.read(ci.chunk_length)
    op, _ = RECORD_HEAD.unpack_from(raw, 0)
    if op != CHUNK_OPCODE or len(raw) != ci.chunk_length:
        raise ValueError(f"no Chunk record at byte {ci.chunk_start_offset}")
    pos = RECORD_HEAD.size + 8 + 8 + 8 + 4  # start, end time; uncompressed size; CRC
    (n_comp,) = struct.unpack_from("<I", raw, pos)
    compression = raw[pos + 4 : pos + 4 + n_comp].decode("utf-8")
    pos += 4 + n_comp
    (n_data,) = struct.unpack_from("<Q", raw, pos)
    data = memoryview(raw)[pos + 8 : pos + 8 + n_data]
    if compression == "":
        return bytes(data[:end])
    if compression == "zstd":
        import zstandard

        reader = zstandard.ZstdDecompressor().stream_reader(data)
        parts = [reader.read(end)]
        n = len(parts[0])
        while n < end and parts[-1]:  # a reader may hand out less than asked
            parts.append(reader.read(end - n))
            n += len(parts[-1])
        return parts[0] if len(parts) == 1 else b"".join(parts)
    import lz4.frame  # mcap's other compression; an ImportError means: stream

    whole: bytes = lz4.frame.decompress(bytes(data))
    return whole[:end]


def _message_at(body: bytes, offset: int) -> tuple[int, int, bytes]:
    """``(channel id, log time, data)`` of the Message record at ``offset`` of a chunk."""
    op, length = RECORD_HEAD.unpack_from(body, offset)
    start = offset + RECORD_HEAD.size
    if op != MESSAGE_OPCODE or length < MESSAGE_HEAD.size or start + length > len(body):
        raise ValueError(f"no Message record at chunk byte {offset}")
    cid, _seq, log_time, _pub = MESSAGE_HEAD.unpack_from(body, start)
    return cid, log_time, body[start + MESSAGE_HEAD.size : start + length]
