"""The records of an MCAP file and of its chunks, read lean.

**The file** (:func:`file_records`). After the 8-byte magic, records follow one
another, each ``opcode (u8) | length (u64) | content``, until the Footer and
the closing magic. A streaming pass needs Header, Schema, Channel, Message,
Chunk, Metadata and the Footer; the library's ``StreamReader`` also parses
every index record entry by entry (a Message Index holds one
``(log_time, offset)`` pair per message of its chunk: two reads each, tens of
thousands a recording), which :func:`file_records` reads past whole. A record
the file ends inside raises :class:`mcap.exceptions.EndOfFile`, as the
library's reader does.

**A chunk** (:func:`chunk_records`): one ``struct`` call per message.

A chunk (MCAP specification, "Chunk" record) holds Schema, Channel and
Message records back to back, each ``opcode (u8) | length (u64) | content``,
after compression (``zstd``, ``lz4`` or none) and with a CRC-32 of the
uncompressed bytes (0: not computed). A Message's content is::

    channel_id u16 | sequence u32 | log_time u64 | publish_time u64 | data

(little-endian). The ``mcap`` library's ``breakup_chunk`` reads each field with
its own call on a byte stream (five per message); a recording holds tens of
thousands of joint-state messages, so :func:`chunk_records` reads a message's
header with one ``struct.unpack_from`` on the decompressed bytes instead and
hands Schema and Channel records (a few per file) to the library's own
readers. The records are the library's classes, equal to what ``breakup_chunk``
returns (``tests/test_mcap_records.py``); a CRC that does not match, a
compression it does not know, or a record that runs past the chunk's end
raise, as the library's reader does, and the caller skips the chunk.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Iterator
from io import BytesIO
from typing import IO

from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile, RecordLengthLimitExceeded
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Footer, Header, McapRecord, Message, Metadata, Schema

_RECORD = struct.Struct("<BQ")
_MESSAGE = struct.Struct("<HIQQ")


def _message(buf: bytes, pos: int, end: int) -> Message:
    """The Message record whose content is ``buf[pos:end]`` (at least 22 bytes)."""
    ch, seq, log_time, publish_time = _MESSAGE.unpack_from(buf, pos)
    return Message(
        channel_id=ch,
        sequence=seq,
        log_time=log_time,
        publish_time=publish_time,
        data=buf[pos + 22 : end],
    )


class ChunkError(ValueError):
    """A chunk that cannot be read (its CRC, compression or a record's length)."""


def chunk_bytes(chunk: Chunk) -> bytes:
    """The chunk's records, decompressed; the CRC checked when the writer stored one."""
    if chunk.compression == "zstd":
        import zstandard

        data: bytes = zstandard.decompress(chunk.data, chunk.uncompressed_size)
    elif chunk.compression == "lz4":
        import lz4.frame

        data = lz4.frame.decompress(chunk.data)
    elif chunk.compression == "":
        data = bytes(chunk.data)
    else:
        raise ChunkError(f"unsupported chunk compression {chunk.compression!r}")
    if chunk.uncompressed_crc != 0:
        crc = zlib.crc32(data)
        if crc != chunk.uncompressed_crc:
            raise ChunkError(
                f"CRC {crc:#010x} of the chunk's bytes, {chunk.uncompressed_crc:#010x} stored"
            )
    return data


def chunk_records(chunk: Chunk) -> list[McapRecord]:
    """The Schema, Channel and Message records of ``chunk`` in order (others skipped)."""
    data = chunk_bytes(chunk)
    out: list[McapRecord] = []
    head = _RECORD.unpack_from
    pos, end = 0, len(data)
    while pos < end:
        if pos + 9 > end:
            raise ChunkError(f"record header at byte {pos} runs past the chunk's end ({end})")
        op, length = head(data, pos)
        pos += 9
        if pos + length > end:
            raise ChunkError(f"record at byte {pos - 9} ({length} bytes) runs past the chunk's end")
        if op == Opcode.MESSAGE:
            if length < 22:
                raise ChunkError(f"message record at byte {pos - 9} is {length} bytes long")
            out.append(_message(data, pos, pos + length))
        elif op == Opcode.CHANNEL:
            out.append(Channel.read(ReadDataStream(BytesIO(data[pos : pos + length]))))
        elif op == Opcode.SCHEMA:
            out.append(Schema.read(ReadDataStream(BytesIO(data[pos : pos + length]))))
        pos += length
    return out


#: the file-level records :func:`file_records` parses (the others are read past whole)
_PARSED = {
    Opcode.HEADER: Header.read,
    Opcode.SCHEMA: Schema.read,
    Opcode.CHANNEL: Channel.read,
    Opcode.METADATA: Metadata.read,
    Opcode.FOOTER: Footer.read,
}
#: the largest record read (as the library's reader: 4 GiB)
RECORD_SIZE_LIMIT = 4 * 2**30
MAGIC = b"\x89MCAP0\r\n"


def _read(f: IO[bytes], n: int) -> bytes:
    b = f.read(n)
    if len(b) < n:
        raise EndOfFile()
    return b


_CHUNK_HEAD = struct.Struct("<QQQII")


def _chunk(f: IO[bytes], length: int) -> Chunk:
    """A Chunk record's content (after its opcode and length), as ``Chunk.read`` reads it."""
    start, end, size, crc, n = _CHUNK_HEAD.unpack(_read(f, 32))
    compression = _read(f, n).decode("utf-8")
    (n_data,) = struct.unpack("<Q", _read(f, 8))
    if 40 + n + n_data > length:
        raise ValueError(f"chunk data of {n_data} bytes overruns its record of {length}")
    data = _read(f, n_data)
    _read(f, length - 40 - n - n_data)  # padding a newer writer may add
    return Chunk(
        compression=compression,
        data=data,
        message_end_time=end,
        message_start_time=start,
        uncompressed_crc=crc,
        uncompressed_size=size,
    )


def file_records(f: IO[bytes]) -> Iterator[McapRecord | None]:
    """The records of the MCAP file ``f`` (at its start) the streaming pass uses, in order.

    Header, Schema, Channel, Message (outside chunks), Chunk (not broken up: see
    :func:`chunk_records`), Metadata, then the Footer, after which it stops. Index,
    statistics, attachment and unknown records are read past, each yielding None. ``f``
    is read record by record, so a caller counting its bytes knows where the last whole
    record ended at each step.

    Raises
    ------
    EndOfFile
        The file ends inside a record (or before the Footer).
    ValueError
        Bad magic, or a record longer than :data:`RECORD_SIZE_LIMIT`.
    """
    if _read(f, 8)[:5] != MAGIC[:5]:
        raise ValueError("not an MCAP file (bad magic)")
    head = _RECORD.unpack
    while True:
        op, length = head(_read(f, 9))
        if length > RECORD_SIZE_LIMIT:
            raise RecordLengthLimitExceeded(op, length, RECORD_SIZE_LIMIT)
        if op == Opcode.CHUNK:  # its header, then the (large) data in one read: one copy
            yield _chunk(f, length)
            continue
        body = _read(f, length)
        if op == Opcode.MESSAGE:
            yield _message(body, 0, length)
            continue
        parse = _PARSED.get(op)
        if parse is None:
            yield None
            continue
        rec = parse(ReadDataStream(BytesIO(body)))
        yield rec
        if op == Opcode.FOOTER:
            _read(f, 8)  # the closing magic
            return
