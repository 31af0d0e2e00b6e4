"""What an MCAP recording cut short still holds: the recorder was killed, the disk filled, the copy stopped.

Such a file has no summary and no footer, and its last record stops part-way; the MCAP reader gives up at the
cut, so everything in it would be lost. :func:`salvage` reads the records before the cut (their CRCs checked
as usual), then the beginning of the chunk the cut went through: a zstd or lz4 chunk is a stream, so the
part of it that was written decompresses to the whole records it holds. What it yields is what a reader of the
whole file would have yielded up to the last whole message; :class:`Cut` says where the cut was.
"""
from __future__ import annotations

import io
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, BinaryIO

from ..runlog.reader import MAGIC

__all__ = ["Cut", "messages", "salvage"]
CHUNK = 0x06  # the chunk record's opcode (MCAP specification)


@dataclass
class Cut:
    """Where the file stopped: the byte offset of the record the cut went through, and the messages salvaged
    from the part of it that was written."""
    offset: int = -1
    from_partial_chunk: int = 0


def _partial_chunk(body: bytes) -> bytes:
    """The records a chunk cut short still holds, decompressed (the last one may stop part-way)."""
    try:
        _start, _end, _size, _crc, n = struct.unpack_from("<QQQII", body, 0)
        compression = body[32:32 + n].decode()
        (length,) = struct.unpack_from("<Q", body, 32 + n)
    except (struct.error, UnicodeDecodeError):
        return b""
    data = body[40 + n:40 + n + length]
    try:
        if compression == "zstd":
            import zstandard

            return bytes(zstandard.ZstdDecompressor().decompressobj().decompress(data))
        if compression == "lz4":
            import lz4.frame

            return bytes(lz4.frame.LZ4FrameDecompressor().decompress(data))
    except Exception:  # the written part is damaged too: nothing from it
        return b""
    return data if compression == "" else b""


def _complete_part(f: BinaryIO) -> tuple[int, int]:
    """(end of the last whole top-level record, offset of the record the cut went through or -1), from the
    records' headers alone (nothing else of the file is read)."""
    size = f.seek(0, io.SEEK_END)
    at = len(MAGIC)
    while at + 9 <= size:
        f.seek(at)
        _op, length = struct.unpack("<BQ", f.read(9))
        if at + 9 + length > size:
            return at, at
        at += 9 + length
    return at, (at if at < size else -1)


class _Upto(io.RawIOBase):
    """The first ``end`` bytes of ``f`` as a stream of their own (read from ``f``'s current position)."""

    def __init__(self, f: BinaryIO, end: int) -> None:
        self.f, self.left = f, end

    def readable(self) -> bool:
        return True

    def readinto(self, b: Any) -> int:
        n = min(len(b), self.left)
        if n <= 0:
            return 0
        got = self.f.readinto(memoryview(b)[:n])  # type: ignore[attr-defined]
        self.left -= got or 0
        return got or 0


def salvage(f: BinaryIO, cut: Cut) -> Iterator[Any]:
    """Every whole record (schemas, channels, messages, metadata...) of the MCAP file ``f`` up to where it was cut,
    in file order, chunks opened; ``cut`` is filled in as the cut is found. The file is streamed: what is held
    in memory at once is a record (a chunk), not the file."""
    from mcap.exceptions import EndOfFile
    from mcap.records import Chunk, Message
    from mcap.stream_reader import StreamReader

    end, cut.offset = _complete_part(f)
    cut.from_partial_chunk = 0
    f.seek(0)
    whole = io.BufferedReader(_Upto(f, end), 1 << 20)
    try:  # whole records only: anything but their end is damage (a CRC that does not match...), said as such
        yield from StreamReader(whole, skip_magic=False, validate_crcs=True).records
    except EndOfFile:
        pass

    def records(reader: StreamReader) -> Iterator[Any]:
        try:
            yield from reader.records
        except Exception:  # where the written part of the chunk stops
            return

    if cut.offset < 0:
        return
    f.seek(cut.offset)
    if f.read(1) != bytes([CHUNK]):
        return
    f.seek(cut.offset + 9)
    for rec in records(StreamReader(io.BytesIO(_partial_chunk(f.read())), skip_magic=True)):
        if isinstance(rec, Chunk):
            break
        cut.from_partial_chunk += isinstance(rec, Message)
        yield rec


def messages(f: BinaryIO, cut: Cut, topics: set[str]) -> Iterator[tuple[Any, Any, Any]]:
    """(schema, channel, message) of every whole message on ``topics`` up to the cut (see :func:`salvage`)."""
    from mcap.records import Channel, Message, Schema

    schemas: dict[int, Any] = {}
    channels: dict[int, Any] = {}
    for rec in salvage(f, cut):
        if isinstance(rec, Schema):
            schemas[rec.id] = rec
        elif isinstance(rec, Channel):
            channels[rec.id] = rec
        elif isinstance(rec, Message) and rec.channel_id in channels:
            ch = channels[rec.channel_id]
            if ch.topic in topics:
                yield schemas.get(ch.schema_id), ch, rec
