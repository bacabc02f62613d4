"""Files of a session recording: the ``.part`` name, the MCAP header, durable renames."""

from __future__ import annotations

import os
import re
from datetime import UTC, datetime
from pathlib import Path
from typing import IO, Any

from posecast.recorder.format import (
    CHANNELS,
    FORMAT_VERSION,
    PROFILE,
    SESSION_METADATA,
    encode_json,
    posecast_version,
)
from posecast.recorder.mcapfile import ChunkWriter
from posecast.recorder.options import RecordOptions

__all__ = ["PART_SUFFIX", "create_part", "fsync_dir", "safe_name", "start_event", "start_file"]

PART_SUFFIX = ".part"


def safe_name(room: str) -> str:
    name = re.sub(r"[^A-Za-z0-9._-]+", "-", room).strip(".-")
    return name[:64] or "room"


def fsync_dir(directory: Path) -> None:
    """Make a rename or a new file in ``directory`` durable, as far as the OS allows."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def create_part(folder: Path, base: str) -> tuple[Path, Path, IO[bytes]]:
    """Create the first free ``BASE[-k].mcap.part`` in ``folder``: part, final path, stream."""
    for k in range(1, 10_000):
        stem = base if k == 1 else f"{base}-{k}"
        final = folder / f"{stem}.mcap"
        part = folder / f"{stem}.mcap{PART_SUFFIX}"
        if final.exists():
            continue
        try:
            return part, final, part.open("xb")
        except FileExistsError:
            continue
    raise FileExistsError(f"no free file name for {base!r} in {folder}")


def start_file(
    stream: IO[bytes], room: str, opts: RecordOptions, start: float, start_wall: float
) -> ChunkWriter:
    """Write the file's header, the session metadata, the schemas and the channels."""
    # Chunks are closed by the recorder (time and size), never by the
    # writer. No message indexes: they would cost 16 B per message
    # outside the chunks, about 5 B per pose; readers find messages
    # through the chunk indexes, and recovery re-indexes from the chunks.
    writer = ChunkWriter(stream)
    writer.start(profile=PROFILE, library=f"posecast-recorder/{posecast_version()}")
    session = {
        "room": room,
        "posecast_version": posecast_version(),
        "format_version": str(FORMAT_VERSION),
        "start_time": repr(start),
        "start_wall_time": repr(start_wall),
        "start_utc": datetime.fromtimestamp(start_wall, UTC).isoformat(),
        "users": encode_json({"users": [dict(u) for u in opts.users]}).decode(),
        "flush_interval": repr(opts.flush_interval),
        "queue_size": str(opts.queue_size),
    }
    session.update(opts.metadata or {})
    writer.add_metadata(SESSION_METADATA, session)
    for spec in CHANNELS:
        schema_id = writer.register_schema(spec.schema_name, spec.schema_encoding, spec.schema_data)
        writer.register_channel(spec.topic, spec.message_encoding, schema_id)
    return writer


def start_event(room: str, start: float) -> dict[str, Any]:
    return {"kind": "recording-start", "room": room, "time": start}
