"""The records of one MCAP chunk, read with one ``struct`` call per message.

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
returns (``tests/test_mcap_chunk.py``); a CRC that does not match, a
compression it does not know, or a record that runs past the chunk's end
raise, as the library's reader does, and the caller skips the chunk.
"""

from __future__ import annotations

import struct
import zlib
from io import BytesIO

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, McapRecord, Message, Schema

_RECORD = struct.Struct("<BQ")
_MESSAGE = struct.Struct("<HIQQ")


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
    head, message = _RECORD.unpack_from, _MESSAGE.unpack_from
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
            ch, seq, log_time, publish_time = message(data, pos)
            out.append(
                Message(
                    channel_id=ch,
                    sequence=seq,
                    log_time=log_time,
                    publish_time=publish_time,
                    data=data[pos + 22 : pos + length],
                )
            )
        elif op == Opcode.CHANNEL:
            out.append(Channel.read(ReadDataStream(BytesIO(data[pos : pos + length]))))
        elif op == Opcode.SCHEMA:
            out.append(Schema.read(ReadDataStream(BytesIO(data[pos : pos + length]))))
        pos += length
    return out
