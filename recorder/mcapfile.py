"""A small, fast MCAP writer for the recorder's own file layout.

The ``mcap`` package's ``Writer`` builds a Python object and several small
writes per message (about 10 us each on our machines), which made the MCAP
framing the largest single cost of recording. :class:`ChunkWriter` writes the
same format (MCAP v0, https://mcap.dev/spec) with one ``struct.pack`` per
message: messages are framed into the open chunk's buffer and the chunk is
compressed, checksummed and written when the recorder closes it
(:meth:`ChunkWriter.flush`). What it writes is what the recorder needs and no
more:

- the data section: header, schema and channel records (outside any chunk, so
  a damaged chunk never takes a channel definition with it), metadata records
  and zstd chunks of message records;
- the summary: schemas, channels, statistics, chunk indexes and metadata
  indexes, each group listed in summary offsets, and a footer with the
  summary's CRC.

No message index records are written (the recorder never wrote them: readers
find messages through the chunk indexes, and recovery re-indexes a file from
its chunks). Files are read back with the ``mcap`` package's readers.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Mapping
from typing import IO, Final

import zstandard

__all__ = ["MAGIC", "ChunkWriter"]

MAGIC: Final = b"\x89MCAP0\r\n"

_HEADER: Final = 0x01
_FOOTER: Final = 0x02
_SCHEMA: Final = 0x03
_CHANNEL: Final = 0x04
_MESSAGE: Final = 0x05
_CHUNK: Final = 0x06
_CHUNK_INDEX: Final = 0x08
_STATISTICS: Final = 0x0B
_METADATA: Final = 0x0C
_METADATA_INDEX: Final = 0x0D
_SUMMARY_OFFSET: Final = 0x0E
_DATA_END: Final = 0x0F

_RECORD_HEAD: Final = struct.Struct("<BQ")
#: opcode, length, channel id, sequence, log time, publish time (the data follows).
_MESSAGE_HEAD: Final = struct.Struct("<BQHIQQ")
_MESSAGE_FIXED: Final = _MESSAGE_HEAD.size - _RECORD_HEAD.size
#: Bytes a message adds to a chunk besides its data.
MESSAGE_OVERHEAD: Final = _MESSAGE_HEAD.size


def _string(value: str) -> bytes:
    data = value.encode()
    return struct.pack("<I", len(data)) + data


def _string_map(values: Mapping[str, str]) -> bytes:
    body = b"".join(_string(k) + _string(v) for k, v in values.items())
    return struct.pack("<I", len(body)) + body


def _record(opcode: int, body: bytes) -> bytes:
    return _RECORD_HEAD.pack(opcode, len(body)) + body


class ChunkWriter:
    """Writes an MCAP file of zstd chunks to ``stream`` (binary, positioned at 0).

    Call :meth:`start`, then register schemas and channels, then add messages
    (into the open chunk) and metadata in any order, :meth:`flush` to close
    the open chunk, and :meth:`finish` to write the summary and footer. The
    stream is never closed here.
    """

    def __init__(self, stream: IO[bytes], *, zstd_level: int = 3) -> None:
        self._stream = stream
        self._offset = 0
        self._compressor = zstandard.ZstdCompressor(level=zstd_level)
        self._schemas: list[bytes] = []
        self._channels: list[bytes] = []
        self._chunk_indexes: list[bytes] = []
        self._metadata_indexes: list[bytes] = []
        self._channel_counts: dict[int, int] = {}
        self._message_count = 0
        self._metadata_count = 0
        self._chunk_count = 0
        self._start_time = 0
        self._end_time = 0
        # The open chunk: framed messages and their time range.
        self._parts: list[bytes] = []
        self._chunk_messages = 0
        self._chunk_start = 0
        self._chunk_end = 0
        self._finished = False

    def _write(self, data: bytes) -> None:
        self._stream.write(data)
        self._offset += len(data)

    def start(self, profile: str = "", library: str = "") -> None:
        """Write the magic and the header record."""
        self._write(MAGIC + _record(_HEADER, _string(profile) + _string(library)))

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        """Write a schema record; returns its id (1, 2, ...)."""
        schema_id = len(self._schemas) + 1
        body = struct.pack("<H", schema_id) + _string(name) + _string(encoding)
        record = _record(_SCHEMA, body + struct.pack("<I", len(data)) + data)
        self._schemas.append(record)
        self._write(record)
        return schema_id

    def register_channel(
        self,
        topic: str,
        message_encoding: str,
        schema_id: int,
        metadata: Mapping[str, str] | None = None,
    ) -> int:
        """Write a channel record; returns its id (1, 2, ...)."""
        channel_id = len(self._channels) + 1
        body = (
            struct.pack("<HH", channel_id, schema_id)
            + _string(topic)
            + _string(message_encoding)
            + _string_map(metadata or {})
        )
        record = _record(_CHANNEL, body)
        self._channels.append(record)
        self._channel_counts[channel_id] = 0
        self._write(record)
        return channel_id

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        """Write a metadata record now (outside any chunk) and index it."""
        record = _record(_METADATA, _string(name) + _string_map(data))
        index = struct.pack("<QQ", self._offset, len(record)) + _string(name)
        self._write(record)
        self._metadata_indexes.append(_record(_METADATA_INDEX, index))
        self._metadata_count += 1

    def add_message(
        self, channel_id: int, log_time: int, data: bytes, publish_time: int, sequence: int
    ) -> None:
        """Frame one message into the open chunk (times in ns, ``sequence`` as u32).

        An unregistered ``channel_id`` raises ``KeyError`` (and adds nothing).
        """
        self._channel_counts[channel_id] += 1
        self._parts += (
            _MESSAGE_HEAD.pack(
                _MESSAGE,
                _MESSAGE_FIXED + len(data),
                channel_id,
                sequence & 0xFFFFFFFF,
                log_time,
                publish_time,
            ),
            data,
        )
        if self._chunk_messages:
            if log_time < self._chunk_start:
                self._chunk_start = log_time
            elif log_time > self._chunk_end:
                self._chunk_end = log_time
        else:
            self._chunk_start = self._chunk_end = log_time
        self._chunk_messages += 1

    def flush(self) -> None:
        """Close the open chunk (if it has messages): compress, write, index it; flush."""
        if self._chunk_messages:
            self._write_chunk()
        self._stream.flush()

    def _write_chunk(self) -> None:
        records = b"".join(self._parts)
        compressed = self._compressor.compress(records)
        body = (
            struct.pack(
                "<QQQI",
                self._chunk_start,
                self._chunk_end,
                len(records),
                zlib.crc32(records),
            )
            + _string("zstd")
            + struct.pack("<Q", len(compressed))
        )
        start = self._offset
        head = _RECORD_HEAD.pack(_CHUNK, len(body) + len(compressed))
        self._write(head + body)
        self._write(compressed)
        index = (
            struct.pack(
                "<QQQQ",
                self._chunk_start,
                self._chunk_end,
                start,
                self._offset - start,
            )
            + struct.pack("<I", 0)  # no message index offsets: none are written
            + struct.pack("<Q", 0)
            + _string("zstd")
            + struct.pack("<QQ", len(compressed), len(records))
        )
        self._chunk_indexes.append(_record(_CHUNK_INDEX, index))
        if self._message_count:
            self._start_time = min(self._start_time, self._chunk_start)
            self._end_time = max(self._end_time, self._chunk_end)
        else:
            self._start_time, self._end_time = self._chunk_start, self._chunk_end
        self._message_count += self._chunk_messages
        self._chunk_count += 1
        self._parts = []
        self._chunk_messages = 0

    def finish(self) -> None:
        """Close the open chunk, write the data end, summary, summary offsets and footer."""
        if self._finished:
            return
        self._finished = True
        if self._chunk_messages:
            self._write_chunk()
        self._write(_record(_DATA_END, struct.pack("<I", 0)))  # no data section CRC
        summary_start = self._offset
        counts = b"".join(struct.pack("<HQ", c, n) for c, n in self._channel_counts.items())
        statistics = _record(
            _STATISTICS,
            struct.pack(
                "<QHIIIIQQ",
                self._message_count,
                len(self._schemas),
                len(self._channels),
                0,  # attachments
                self._metadata_count,
                self._chunk_count,
                self._start_time,
                self._end_time,
            )
            + struct.pack("<I", len(counts))
            + counts,
        )
        groups = [
            (_SCHEMA, self._schemas),
            (_CHANNEL, self._channels),
            (_STATISTICS, [statistics]),
            (_CHUNK_INDEX, self._chunk_indexes),
            (_METADATA_INDEX, self._metadata_indexes),
        ]
        summary = bytearray()
        offsets = bytearray()
        for opcode, records in groups:
            if not records:
                continue
            group = b"".join(records)
            offsets += _record(
                _SUMMARY_OFFSET,
                struct.pack("<BQQ", opcode, summary_start + len(summary), len(group)),
            )
            summary += group
        summary_offset_start = summary_start + len(summary)
        summary += offsets
        footer_head = struct.pack("<BQQQ", _FOOTER, 20, summary_start, summary_offset_start)
        crc = zlib.crc32(footer_head, zlib.crc32(summary))
        self._write(bytes(summary) + footer_head + struct.pack("<I", crc) + MAGIC)
        self._stream.flush()
