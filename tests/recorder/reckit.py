"""Helpers for the recorder tests: synthetic sessions and an independent MCAP oracle."""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from mcap.records import Chunk, Message
from mcap.stream_reader import StreamReader, breakup_chunk

from posecast.recorder import SessionRecorder

__all__ = [
    "T0",
    "Msg",
    "OracleChunk",
    "Update",
    "make_updates",
    "messages_of",
    "oracle_chunks",
    "write_session",
]

T0 = 1000.0


@dataclass(frozen=True)
class Update:
    """One pose update as handed to the recorder."""

    user: int
    seq: int
    arrival: float
    streams: np.ndarray
    capture_times: np.ndarray
    poses: np.ndarray


def make_updates(count: int, users: int = 4, seed: int = 0) -> list[Update]:
    """Updates of 1-3 streams with random float32 poses, 20 Hz per user, in arrival order."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(count):
        user = k % users
        n = 1 + (k // users) % 3
        arrival = T0 + k / (20.0 * users) + float(rng.uniform(0, 1e-3))
        caps = arrival - rng.uniform(0.01, 0.05, n)
        poses = rng.normal(size=(n, 7)).astype(np.float32)
        streams = np.arange(3 * user, 3 * user + n, dtype=np.uint16)
        out.append(Update(user, k // users, arrival, streams, caps, poses))
    return out


def write_session(
    directory: Path, updates: list[Update], chunk_records: int | None = None, **kwargs: object
) -> Path:
    """Record the updates plus a presence join per user and an event every 50 updates."""
    rec = SessionRecorder.open(
        directory,
        "test-room",
        name="session",
        clock=lambda: T0,
        chunk_records=chunk_records,
        **kwargs,  # type: ignore[arg-type]
    )
    joined: set[int] = set()
    for i, u in enumerate(updates):
        if u.user not in joined:
            joined.add(u.user)
            streams = {name: 3 * u.user + j for j, name in enumerate(("head", "left", "right"))}
            rec.record_presence(
                {"kind": "join", "user": u.user, "name": f"bot{u.user}", "streams": streams},
                time=u.arrival,
            )
        rec.record_update(u.user, u.seq, u.arrival, u.streams, u.capture_times, u.poses)
        if i % 50 == 49:
            rec.record_event({"kind": "button", "user": u.user, "time": u.arrival})
    return rec.close(time=updates[-1].arrival if updates else T0)


#: A message as compared across files: topic, sequence, log time, publish time, data.
Msg = tuple[str, int, int, int, bytes]


@dataclass(frozen=True)
class OracleChunk:
    """A chunk of an intact file as mcap's own readers see it."""

    offset: int
    length: int
    messages: list[Msg]


def oracle_chunks(data: bytes) -> list[OracleChunk]:
    """Chunks of a finished file: offsets from its summary, messages via mcap's StreamReader."""
    summary = make_reader(io.BytesIO(data)).get_summary()
    assert summary is not None
    topics = {cid: ch.topic for cid, ch in summary.channels.items()}
    chunks = [
        r for r in StreamReader(io.BytesIO(data), emit_chunks=True).records if isinstance(r, Chunk)
    ]
    indexes = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    assert len(chunks) == len(indexes)
    out = []
    for chunk, index in zip(chunks, indexes, strict=True):
        msgs = [
            (topics[m.channel_id], m.sequence, m.log_time, m.publish_time, bytes(m.data))
            for m in breakup_chunk(chunk, validate_crc=True)
            if isinstance(m, Message)
        ]
        out.append(OracleChunk(index.chunk_start_offset, index.chunk_length, msgs))
    return out


def messages_of(path: Path) -> list[Msg]:
    """Every message of a finished file in file order, via mcap's indexed reader."""
    with path.open("rb") as f:
        reader = make_reader(f)
        return [
            (ch.topic, m.sequence, m.log_time, m.publish_time, bytes(m.data))
            for _s, ch, m in reader.iter_messages(log_time_order=False)
        ]
