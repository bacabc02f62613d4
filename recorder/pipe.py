"""The pipe between the relay's :class:`~recorder.host.RecorderHost` and its writer process.

Both ends share what is here: the frame and message layouts, :func:`_frame`, and
the writer process's exit codes (:mod:`recorder.writerproc` is the child's end).

Pipe frames (little-endian): ``u8 kind, u32 length, u32 room id`` + payload:
``OPEN``: the room's configuration as JSON; ``BATCH``: messages of that room,
each ``u8 kind, u32 length, payload``: ``UPDATE``: ``u16 user, u32 poses, f64
arrival, u64 seq, f64 base time`` + the update's entries
(:data:`protocol.UPDATE_DTYPE` or, for the velocity variant,
:data:`protocol.UPDATE_VELOCITY_DTYPE` records: their size tells which);
``COMPACT``: as ``UPDATE`` plus ``u8 codes per entry (7 or 13), f64[6] room
volume (lo, hi)`` + the entries + their codes (i64 each, entry by entry; the
update of a compact session, recorded as layout 2);
``RECORD``: ``u8 channel index, i64 log ns, i64 publish ns, u32 poses`` + data;
``STOP``: ``f64 end time`` (the room's last message). The child's standard
output carries JSON lines, each with the room id: ``{"event": "ready", "room":
id, "part": ..., "path": ...}`` once the room's file is open, ``{"event":
"closed", "room": id, "statistics": {...}}`` at its end and ``{"event":
"error", "room": id, "error": ...}`` (room ``null``: the whole process).
"""

from __future__ import annotations

import os
import struct
from pathlib import Path
from typing import Any, Final

from posecast.protocol.poses import UPDATE_DTYPE, UPDATE_VELOCITY_DTYPE
from posecast.recorder.format import CHANNELS
from posecast.recorder.options import RecordOptions

__all__ = ["EXIT_ERROR", "EXIT_OK", "EXIT_RELAY_GONE"]

# Frames of the pipe: kind, length, room id.
_FRAME_OPEN: Final = 1
_FRAME_BATCH: Final = 2
_FRAME: Final = struct.Struct("<BII")
# Messages inside a batch.
_KIND_UPDATE: Final = 1
_KIND_RECORD: Final = 2
_KIND_STOP: Final = 3
_KIND_COMPACT: Final = 4
_HEAD: Final = struct.Struct("<BI")
# head + user, poses, arrival, seq, base time (the entries' size tells their layout)
_UPDATE: Final = struct.Struct("<BIHIdQd")
_UPDATE_EXTRA: Final = _UPDATE.size - _HEAD.size
_UPDATE_PACK: Final = _UPDATE.pack
# head + user, poses, arrival, seq, base time, codes per entry, volume (lo, hi)
_COMPACT: Final = struct.Struct("<BIHIdQdB6d")
_COMPACT_EXTRA: Final = _COMPACT.size - _HEAD.size
_VOLUME: Final = struct.Struct("<6d")
#: Packs the header without the volume (whose bytes the relay keeps packed).
_COMPACT_PACK: Final = struct.Struct("<BIHIdQdB").pack
_CODE_STRUCTS: dict[int, struct.Struct] = {}


def _codes_struct(count: int) -> struct.Struct:
    """The struct of ``count`` codes (i64 each), made once per count."""
    packer = _CODE_STRUCTS.get(count)
    if packer is None:
        packer = _CODE_STRUCTS[count] = struct.Struct(f"<{count}q")
    return packer


_PLAIN_ITEM: Final = UPDATE_DTYPE.itemsize
_VELOCITY_ITEM: Final = UPDATE_VELOCITY_DTYPE.itemsize
_RECORD: Final = struct.Struct("<BIBqqI")  # head + channel, log ns, publish ns, poses
_RECORD_EXTRA: Final = _RECORD.size - _HEAD.size
_STOP: Final = struct.Struct("<BId")
#: What a frame's length counts beyond the kind and length: the room id.
_FRAME_EXTRA: Final = _FRAME.size - _HEAD.size
_TOPICS: Final = [spec.topic for spec in CHANNELS]
_CHANNEL_INDEX: Final = {topic: i for i, topic in enumerate(_TOPICS)}
#: The child's exit codes: all rooms finished; a room or the pipe was bad; the relay vanished.
EXIT_OK: Final = 0
EXIT_ERROR: Final = 1
EXIT_RELAY_GONE: Final = 2


def _frame(kind: int, room: int, payload_size: int) -> bytes:
    return _FRAME.pack(kind, _FRAME_EXTRA + payload_size, room)


def _room_config(
    directory: str | os.PathLike[str], room: str, opts: RecordOptions
) -> dict[str, Any]:
    """The configuration an ``OPEN`` frame carries (its JSON is the frame's payload)."""
    return {
        "directory": str(Path(directory).resolve()),
        "room": room,
        "name": opts.name,
        "users": [dict(u) for u in opts.users],
        "start": opts.clock(),
        "start_wall": opts.wall_clock(),
        "queue_size": opts.queue_size,
        "flush_interval": opts.flush_interval,
        "chunk_bytes": opts.chunk_bytes,
        "metadata": dict(opts.metadata or {}),
    }
