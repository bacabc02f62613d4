"""A forgiving, linear reader of MCAP bytes: every intact chunk, nothing else.

MCAP is a magic string (``\\x89MCAP0\\r\\n``) followed by records, each an opcode
(u8), a body length (u64) and the body. :class:`McapScanner` walks the data
section record by record and yields what a recording needs (header, schemas,
channels, messages, metadata). It trusts nothing:

- a Chunk is opened with its own framing (times, uncompressed size and CRC,
  compression name, length of its records) and must agree with the record's
  length; it is decompressed and its records are kept only if the CRC32 of the
  uncompressed bytes matches (and they parse): a chunk is kept whole or lost
  whole, and each lost chunk is reported (offset, reason, time range);
- a record whose length runs past the end of the file is a truncated tail, unless
  an intact chunk follows further on, in which case its length field was
  corrupted: the scanner resynchronises on the next chunk that passes the same
  checks, and reports the bytes it skipped;
- a chunk whose length field was damaged but whose inner framing is intact and
  whose CRC matches is kept (reported as repaired);
- unknown opcodes, or summary records inside the data section, are corruption too.

Scanning stops at the Data End record (the summary that follows is rebuilt by
whoever writes the recovered file), at a truncated tail, or at the end of the
bytes. Messages written outside chunks carry no CRC; they are yielded as well
but counted separately (``unchunked_messages``). Nothing here writes files.
"""

from __future__ import annotations

import mmap
import struct
import zlib
from collections.abc import Generator, Iterator
from dataclasses import dataclass
from typing import Final

import zstandard

try:  # mcap treats lz4 as optional; so do we (posecast writes zstd chunks)
    import lz4.frame as _lz4
except ImportError:  # pragma: no cover - depends on the environment
    _lz4 = None

__all__ = [
    "MAGIC",
    "ChannelRecord",
    "HeaderRecord",
    "McapScanner",
    "MessageRecord",
    "MetadataRecord",
    "ScanProblem",
    "ScannedRecord",
    "SchemaRecord",
]

MAGIC: Final = b"\x89MCAP0\r\n"

_HEADER, _FOOTER, _SCHEMA, _CHANNEL, _MESSAGE, _CHUNK = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
_MESSAGE_INDEX, _ATTACHMENT, _METADATA, _DATA_END = 0x07, 0x09, 0x0C, 0x0F
#: Records that may appear in the data section; anything else there is corruption.
_DATA_OPCODES: Final = frozenset(
    {_HEADER, _SCHEMA, _CHANNEL, _MESSAGE, _CHUNK, _MESSAGE_INDEX, _ATTACHMENT, _METADATA}
)
_COMPRESSIONS: Final = ("", "zstd", "lz4")
#: Refuse to decompress chunks claiming more than this (a corrupted size field).
_MAX_UNCOMPRESSED: Final = 1 << 31

_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
_OP_LEN = struct.Struct("<BQ")
_CHUNK_HEAD = struct.Struct("<QQQI")  # start, end, uncompressed size, crc
_MSG_HEAD = struct.Struct("<HIQQ")  # channel, sequence, log time, publish time


_Buffer = bytes | mmap.mmap


class _Malformed(Exception):
    """A record body that does not parse."""


@dataclass(frozen=True)
class HeaderRecord:
    """The MCAP Header: profile (``posecast`` for session files) and writer library."""

    profile: str
    library: str


@dataclass(frozen=True)
class SchemaRecord:
    """An MCAP Schema record."""

    id: int
    name: str
    encoding: str
    data: bytes


@dataclass(frozen=True)
class ChannelRecord:
    """An MCAP Channel record."""

    id: int
    schema_id: int
    topic: str
    message_encoding: str
    metadata: dict[str, str]


@dataclass(frozen=True)
class MessageRecord:
    """An MCAP Message record; ``chunk`` is the offset of its chunk (-1: outside any)."""

    channel_id: int
    sequence: int
    log_time: int
    publish_time: int
    data: bytes
    chunk: int


@dataclass(frozen=True)
class MetadataRecord:
    """An MCAP Metadata record."""

    name: str
    metadata: dict[str, str]


ScannedRecord = HeaderRecord | SchemaRecord | ChannelRecord | MessageRecord | MetadataRecord


@dataclass(frozen=True)
class ScanProblem:
    """Something the scanner had to skip, repair or stop at.

    ``kind``: ``bad-chunk`` (CRC, decompression, framing: the chunk is lost),
    ``repaired`` (chunk kept despite a damaged length field), ``resync`` (bytes
    skipped after a corrupted record, up to the next intact chunk), ``truncated``
    (the file ends inside a record), ``bad-magic``, ``bad-record`` (a record
    outside chunks that does not parse). ``length`` is the number of bytes
    skipped; ``start_time``/``end_time`` the lost chunk's message log times (ns)
    when its header was readable.
    """

    offset: int
    length: int
    kind: str
    reason: str
    start_time: int | None = None
    end_time: int | None = None


@dataclass(frozen=True)
class _ChunkFrame:
    start: int
    end: int
    uncompressed_size: int
    crc: int
    compression: str
    records_start: int
    records_end: int

    @property
    def body_length(self) -> int:
        return self.records_end - self.records_start + 40 + len(self.compression)


def _string(buf: _Buffer, pos: int, end: int) -> tuple[str, int]:
    if pos + 4 > end:
        raise _Malformed("string length past the end of the record")
    (n,) = _U32.unpack_from(buf, pos)
    pos += 4
    if pos + n > end:
        raise _Malformed("string past the end of the record")
    try:
        return bytes(buf[pos : pos + n]).decode(), pos + n
    except UnicodeDecodeError as exc:
        raise _Malformed("string is not UTF-8") from exc


def _string_map(buf: _Buffer, pos: int, end: int) -> tuple[dict[str, str], int]:
    if pos + 4 > end:
        raise _Malformed("map length past the end of the record")
    (n,) = _U32.unpack_from(buf, pos)
    pos += 4
    stop = pos + n
    if stop > end:
        raise _Malformed("map past the end of the record")
    out: dict[str, str] = {}
    while pos < stop:
        key, pos = _string(buf, pos, stop)
        value, pos = _string(buf, pos, stop)
        out[key] = value
    return out, stop


def _parse(op: int, buf: _Buffer, pos: int, end: int, chunk: int) -> ScannedRecord | None:
    """Parse a record body ``buf[pos:end]``; None for records a recording does not need."""
    try:
        if op == _MESSAGE:
            if pos + _MSG_HEAD.size > end:
                raise _Malformed("message shorter than its header")
            channel, seq, log_time, pub_time = _MSG_HEAD.unpack_from(buf, pos)
            data = bytes(buf[pos + _MSG_HEAD.size : end])
            return MessageRecord(channel, seq, log_time, pub_time, data, chunk)
        if op == _SCHEMA:
            if pos + 2 > end:
                raise _Malformed("schema shorter than its header")
            (ident,) = _U16.unpack_from(buf, pos)
            name, p = _string(buf, pos + 2, end)
            encoding, p = _string(buf, p, end)
            if p + 4 > end:
                raise _Malformed("schema data length past the end")
            (n,) = _U32.unpack_from(buf, p)
            if p + 4 + n != end:
                raise _Malformed("schema data does not fill the record")
            return SchemaRecord(ident, name, encoding, bytes(buf[p + 4 : end]))
        if op == _CHANNEL:
            if pos + 4 > end:
                raise _Malformed("channel shorter than its header")
            ident, schema_id = struct.unpack_from("<HH", buf, pos)
            topic, p = _string(buf, pos + 4, end)
            encoding, p = _string(buf, p, end)
            meta, p = _string_map(buf, p, end)
            if p != end:
                raise _Malformed("channel record has trailing bytes")
            return ChannelRecord(ident, schema_id, topic, encoding, meta)
        if op == _METADATA:
            name, p = _string(buf, pos, end)
            meta, p = _string_map(buf, p, end)
            if p != end:
                raise _Malformed("metadata record has trailing bytes")
            return MetadataRecord(name, meta)
        if op == _HEADER:
            profile, p = _string(buf, pos, end)
            library, p = _string(buf, p, end)
            return HeaderRecord(profile, library)
    except struct.error as exc:
        raise _Malformed(str(exc)) from exc
    return None


class McapScanner:
    """Walks MCAP bytes (``bytes``, ``mmap``, ...) once; see the module docstring.

    Iterate :meth:`records`; afterwards the attributes describe what was found.
    """

    def __init__(self, data: bytes | mmap.mmap) -> None:
        self._buf = data
        self.size = len(data)
        self.problems: list[ScanProblem] = []
        self.header: HeaderRecord | None = None
        self.chunks_ok = 0
        self.chunks_lost = 0
        self.unchunked_messages = 0
        self.complete = False
        """True if the Data End record was reached (the writer finished the file)."""
        self.truncated_at: int | None = None
        """Offset of the record the file ends inside, or None."""
        self.end_offset = 0
        """Where scanning stopped."""
        self._decompressor = zstandard.ZstdDecompressor()
        self._found: tuple[int, list[ScannedRecord]] | None = None

    # -- chunks ------------------------------------------------------------------------

    def _frame(self, pos: int) -> _ChunkFrame | None:
        """The inner framing of a chunk record at ``pos`` if it is self-consistent."""
        buf, size = self._buf, self.size
        b = pos + 9
        if b + 32 > size:
            return None
        start, end, usize, crc = _CHUNK_HEAD.unpack_from(buf, b)
        (clen,) = _U32.unpack_from(buf, b + 28)
        if clen > 8 or b + 32 + clen + 8 > size:
            return None
        try:
            compression = bytes(buf[b + 32 : b + 32 + clen]).decode("ascii")
        except UnicodeDecodeError:
            return None
        if compression not in _COMPRESSIONS or start > end or usize > _MAX_UNCOMPRESSED:
            return None
        (rlen,) = _U64.unpack_from(buf, b + 32 + clen)
        rstart = b + 40 + clen
        return _ChunkFrame(start, end, usize, crc, compression, rstart, rstart + rlen)

    def _open_chunk(self, pos: int, frame: _ChunkFrame) -> list[ScannedRecord] | str:
        """The chunk's records, or why it cannot be trusted."""
        data = bytes(self._buf[frame.records_start : frame.records_end])
        try:
            if frame.compression == "zstd":
                raw = self._decompressor.decompress(data, max_output_size=frame.uncompressed_size)
            elif frame.compression == "lz4":
                if _lz4 is None:
                    return "lz4 chunk, but the lz4 package is not installed"
                raw = _lz4.decompress(data)
            else:
                raw = data
        except Exception as exc:  # zstd and lz4 raise their own error types
            return f"decompression failed: {exc}"
        if len(raw) != frame.uncompressed_size:
            return f"decompressed to {len(raw)} bytes, header says {frame.uncompressed_size}"
        if frame.crc != 0 and zlib.crc32(raw) != frame.crc:
            return f"CRC mismatch (stored {frame.crc:08x}, computed {zlib.crc32(raw):08x})"
        out: list[ScannedRecord] = []
        p, end = 0, len(raw)
        while p < end:
            if p + 9 > end:
                return "chunk records end inside a record header"
            op, length = _OP_LEN.unpack_from(raw, p)
            if p + 9 + length > end:
                return "chunk record runs past the end of the chunk"
            try:
                rec = _parse(op, raw, p + 9, p + 9 + length, pos)
            except _Malformed as exc:
                return f"malformed record in chunk: {exc}"
            if rec is not None:
                out.append(rec)
            p += 9 + length
        return out

    def _intact_chunk(self, pos: int) -> list[ScannedRecord] | None:
        """Records of an intact chunk whose record starts at ``pos`` (framing agrees)."""
        if self._buf[pos] != _CHUNK or pos + 9 > self.size:
            return None
        frame = self._frame(pos)
        if frame is None or frame.records_end > self.size:
            return None
        (length,) = _U64.unpack_from(self._buf, pos + 1)
        if length != frame.body_length:
            return None
        recs = self._open_chunk(pos, frame)
        return recs if isinstance(recs, list) else None

    def _resync(self, start: int) -> int | None:
        """Offset of the next intact chunk at or after ``start``, or None."""
        buf = self._buf
        find = buf.find
        p = start
        while True:
            p = find(b"\x06", p)
            if p < 0 or p + 9 > self.size:
                return None
            recs = self._intact_chunk(p)
            if recs is not None:
                self._found = (p, recs)
                return p
            p += 1

    def _take_found(self, pos: int) -> list[ScannedRecord] | None:
        found, self._found = self._found, None
        if found is not None and found[0] == pos:
            return found[1]
        return None

    # -- the walk ----------------------------------------------------------------------

    def _skip_to_next_chunk(self, pos: int, reason: str) -> int | None:
        """Resynchronise after corruption at ``pos``; report the skipped bytes."""
        nxt = self._resync(pos + 1)
        length = (self.size if nxt is None else nxt) - pos
        self.problems.append(ScanProblem(pos, length, "resync", reason))
        return nxt

    def records(self) -> Iterator[ScannedRecord]:
        """Yield every record that can be trusted, in file order."""
        buf, size = self._buf, self.size
        if size >= 8 and bytes(buf[:8]) == MAGIC:
            pos: int | None = 8
        elif MAGIC.startswith(bytes(buf[:8])):
            self._truncated(0, "file ends inside the magic")
            return
        else:
            pos = self._resync(0)
            self.problems.append(
                ScanProblem(0, size if pos is None else pos, "bad-magic", "no MCAP magic")
            )
        while pos is not None:
            self.end_offset = pos
            if pos >= size:
                break
            if pos + 9 > size:
                self.truncated_at = pos
                self.problems.append(
                    ScanProblem(pos, size - pos, "truncated", "file ends in a record header")
                )
                break
            op, length = _OP_LEN.unpack_from(buf, pos)
            body, end = pos + 9, pos + 9 + length
            if (op, length) in ((_DATA_END, 4), (_FOOTER, 20)):
                self.complete = True
                self.end_offset = min(end, size)
                break
            if op == _CHUNK:
                recs = self._take_found(pos)
                if recs is not None:
                    self.chunks_ok += 1
                    yield from recs
                    pos = end
                    continue
                pos = yield from self._chunk(pos, length)
                continue
            if op not in _DATA_OPCODES:
                pos = self._skip_to_next_chunk(pos, f"unexpected opcode 0x{op:02x}")
                continue
            if end > size:
                nxt = self._resync(pos + 1)
                if nxt is None:
                    self._truncated(pos, f"record (opcode 0x{op:02x}) runs past the end")
                    break
                self.problems.append(
                    ScanProblem(pos, nxt - pos, "resync", f"bad length of opcode 0x{op:02x}")
                )
                pos = nxt
                continue
            try:
                rec = _parse(op, buf, body, end, -1)
            except _Malformed as exc:
                pos = self._skip_to_next_chunk(pos, f"malformed record 0x{op:02x}: {exc}")
                continue
            if isinstance(rec, HeaderRecord):
                self.header = rec
            elif isinstance(rec, MessageRecord):
                self.unchunked_messages += 1
            if rec is not None:
                yield rec
            pos = end
        else:
            self.end_offset = size

    def _truncated(self, pos: int, reason: str) -> None:
        self.truncated_at = pos
        self.problems.append(ScanProblem(pos, self.size - pos, "truncated", reason))

    def _chunk(self, pos: int, length: int) -> Generator[ScannedRecord, None, int | None]:
        """Yield the chunk's records at ``pos``; return where to go on (None: stop)."""
        size = self.size
        frame = self._frame(pos)
        end = pos + 9 + length
        if frame is None:
            if end > size:
                nxt = self._resync(pos + 1)
                if nxt is None:
                    self._truncated(pos, "chunk runs past the end of the file")
                    self.end_offset = pos
                    return None
                self.chunks_lost += 1
                self.problems.append(
                    ScanProblem(pos, nxt - pos, "bad-chunk", "unreadable chunk header")
                )
                return nxt
            self.chunks_lost += 1
            return self._skip_to_next_chunk(pos, "unreadable chunk header")
        times = (frame.start, frame.end)
        agrees = length == frame.body_length
        if frame.records_end > size:
            # Cut off (or a corrupted length in the header): an intact chunk later on
            # means corruption, none means a truncated tail.
            nxt = self._resync(pos + 1)
            if nxt is None:
                self._truncated(pos, "chunk runs past the end of the file")
                return None
            self.chunks_lost += 1
            self.problems.append(
                ScanProblem(pos, nxt - pos, "bad-chunk", "chunk framing runs past the end", *times)
            )
            return nxt
        recs = self._open_chunk(pos, frame)
        if isinstance(recs, list):
            self.chunks_ok += 1
            if not agrees:
                self.problems.append(
                    ScanProblem(
                        pos,
                        0,
                        "repaired",
                        f"chunk length field says {length}, its framing {frame.body_length}:"
                        " kept (CRC matches)",
                        *times,
                    )
                )
            yield from recs
            return pos + 9 + frame.body_length
        self.chunks_lost += 1
        if agrees:
            # Framing is consistent, only the contents are bad: skip exactly this chunk.
            self.problems.append(ScanProblem(pos, 9 + length, "bad-chunk", recs, *times))
            return end
        nxt = self._resync(pos + 1)
        skipped = (size if nxt is None else nxt) - pos
        self.problems.append(
            ScanProblem(pos, skipped, "bad-chunk", f"{recs}; length field disagrees", *times)
        )
        return nxt
