"""The writer process of a :class:`~recorder.host.RecorderHost`: :func:`main` is its entry.

Started by :meth:`RecorderHost.start` (``python -c "... posecast.recorder.writerproc
import main ..."``), it reads the pipe (layout in :mod:`recorder.pipe`) from its
standard input, encodes each room's updates in groups of the same shape (a
compact session's updates go to the writer thread as codes, for layout 2) and
records them with one :class:`SessionRecorder` per room (same file layout,
chunking, fsync schedule, ``.part`` and rename), and answers on its standard
output with JSON lines. If the relay dies, it sees the pipe close without the
rooms' stops, makes what it received durable and leaves every open room's
``.part`` for recovery.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import select
import signal
import struct
import sys
import threading
from collections.abc import Mapping
from dataclasses import asdict
from typing import Any, Final

import numpy as np

from posecast.protocol.codec import Volume
from posecast.protocol.poses import UPDATE_DTYPE, UPDATE_VELOCITY_DTYPE
from posecast.recorder.compact import CompactUpdate, newest_ns
from posecast.recorder.format import POSES_TOPIC, encode_pose_batch, to_ns, to_ns_many
from posecast.recorder.options import RecordOptions
from posecast.recorder.pipe import (
    _COMPACT,
    _FRAME,
    _FRAME_BATCH,
    _FRAME_OPEN,
    _HEAD,
    _KIND_COMPACT,
    _KIND_RECORD,
    _KIND_STOP,
    _KIND_UPDATE,
    _PLAIN_ITEM,
    _RECORD,
    _STOP,
    _TOPICS,
    _UPDATE,
    _VELOCITY_ITEM,
    EXIT_ERROR,
    EXIT_OK,
    EXIT_RELAY_GONE,
)
from posecast.recorder.tap import RecorderError
from posecast.recorder.writer import SessionRecorder

__all__ = ["main"]

log = logging.getLogger("posecast.recorder")

#: The child's own hand-off to a room's writer thread: records per batch, seconds at most.
_CHILD_BATCH: Final = 256
_CHILD_BATCH_DELAY: Final = 0.05
#: Niceness the writer process adds to its own (a lower CPU priority than the relay's).
_CHILD_NICE: Final = 10

_emit_lock = threading.Lock()


def _emit(event: Mapping[str, Any]) -> None:
    with _emit_lock:
        sys.stdout.write(json.dumps(event) + "\n")
        sys.stdout.flush()


#: One update from the pipe: user, poses, arrival, seq, base time, entries.
_Update = tuple[int, int, float, int, float, bytes]


def _record_updates(rec: SessionRecorder, updates: list[_Update]) -> None:
    """Record consecutive updates, encoding same-shaped ones together.

    Each group of updates with the same number of streams and layout is encoded
    in a few numpy passes (:func:`encode_pose_batch`, the same bytes as
    :func:`encode_pose`); records are offered in the pipe's order. An update
    whose entries do not match its header is refused and counted.
    """
    out: list[tuple[int, int, bytes, int] | None] = [None] * len(updates)
    groups: dict[tuple[int, bool], list[int]] = {}
    for i, (_user, n, _arrival, _seq, _base, body) in enumerate(updates):
        size = len(body)
        if size == n * _PLAIN_ITEM:
            groups.setdefault((n, False), []).append(i)
        elif size == n * _VELOCITY_ITEM:
            groups.setdefault((n, True), []).append(i)
    for (n, velocity), idx in groups.items():
        dtype = UPDATE_VELOCITY_DTYPE if velocity else UPDATE_DTYPE
        rows = [updates[i] for i in idx]
        entries = np.frombuffer(b"".join(r[5] for r in rows), dtype).reshape(len(rows), n)
        bases = np.array([r[4] for r in rows])
        caps = entries["dt"].astype(np.float64) + bases[:, None]
        arrivals = np.array([r[2] for r in rows])
        datas = encode_pose_batch(
            [r[0] for r in rows],
            np.array([r[3] for r in rows], dtype=np.uint64),
            arrivals,
            entries["stream"],
            caps,
            entries["pose"],
            entries["velocity"] if velocity else None,
        )
        # publish time: the newest capture time of the update (its arrival if empty)
        newest = caps.max(axis=1) if n else arrivals
        for i, log_ns, pub_ns, data in zip(
            idx, to_ns_many(arrivals), to_ns_many(newest), datas, strict=True
        ):
            out[i] = (log_ns, pub_ns, data, n)
    encoded = []
    for update, done in zip(updates, out, strict=True):
        if done is None:
            rec.refuse(POSES_TOPIC, f"update of user {update[0]}: entries do not match its header")
        else:
            encoded.append(done)
    rec.offer_encoded_many(POSES_TOPIC, encoded)


_volumes: dict[tuple[float, ...], Volume] = {}


def _compact(body: bytearray, at: int, end: int) -> CompactUpdate | None:
    """The compact update of the ``COMPACT`` message ``body[at:end]`` (None if malformed)."""
    if end - at < _COMPACT.size:
        raise ValueError("a compact update message is shorter than its header")
    _k, _n, user, n, arrival, seq, base, width, *box = _COMPACT.unpack_from(body, at)
    data = bytes(body[at + _COMPACT.size : end])
    entries_size = len(data) - 8 * width * n
    if width not in (7, 13) or entries_size not in (n * _PLAIN_ITEM, n * _VELOCITY_ITEM):
        return None
    dtype = UPDATE_VELOCITY_DTYPE if width == 13 else UPDATE_DTYPE
    if dtype.itemsize * n != entries_size:
        return None
    key = tuple(box)
    volume = _volumes.get(key)
    if volume is None:
        volume = _volumes[key] = Volume((box[0], box[1], box[2]), (box[3], box[4], box[5]))
    entries = np.frombuffer(data, dtype, n)
    codes = np.frombuffer(data, "<i8", width * n, entries_size).reshape(n, width)
    return CompactUpdate(
        user,
        seq,
        arrival,
        base,
        entries["stream"],
        entries["dt"],
        codes.astype(np.int64),
        entries["pose"],
        entries["velocity"] if width == 13 else None,
        volume,
    )


def _record_batch(rec: SessionRecorder, body: bytearray, at: int, end: int) -> float | None:
    """Record a room's batch, ``body[at:end]``; the stop's end time if it ends the room."""
    head_size = _HEAD.size
    update_at, record_at = _UPDATE.size, _RECORD.size
    updates: list[_Update] = []
    stop: float | None = None
    while at < end:
        if end - at < head_size:
            raise ValueError("a batch ends inside a message header")
        kind, length = _HEAD.unpack_from(body, at)
        nxt = at + head_size + length
        if nxt > end:
            raise ValueError("a message runs past the end of its batch")
        if kind == _KIND_UPDATE:
            if nxt - at < update_at:
                raise ValueError("an update message is shorter than its header")
            head = _UPDATE.unpack_from(body, at)
            updates.append((*head[2:], bytes(body[at + update_at : nxt])))
        else:
            # Keep the file's record order: the updates before this record first.
            if updates:
                _record_updates(rec, updates)
                updates = []
            if kind == _KIND_COMPACT:
                update = _compact(body, at, nxt)
                if update is None:
                    rec.refuse(POSES_TOPIC, "compact update: entries do not match its header")
                else:
                    log_ns, pub_ns = to_ns(update.arrival), newest_ns(update)
                    rec.offer_encoded(POSES_TOPIC, log_ns, pub_ns, update, len(update.streams))
            elif kind == _KIND_RECORD:
                _k, _n, channel, log_ns, pub_ns, poses = _RECORD.unpack_from(body, at)
                data = bytes(body[at + record_at : nxt])
                rec.offer_encoded(_TOPICS[channel], log_ns, pub_ns, data, poses)
            elif kind == _KIND_STOP:
                stop = float(_STOP.unpack_from(body, at)[2])
            else:
                raise ValueError(f"unknown message kind {kind}")
        at = nxt
    if updates:
        _record_updates(rec, updates)
    return stop


def _open_room(room_id: int, config: Mapping[str, Any]) -> SessionRecorder | None:
    start, start_wall = float(config["start"]), float(config["start_wall"])
    try:
        options = RecordOptions(
            name=config.get("name"),
            users=config.get("users", ()),
            clock=lambda: start,
            wall_clock=lambda: start_wall,
            queue_size=int(config["queue_size"]),
            flush_interval=float(config["flush_interval"]),
            chunk_bytes=int(config["chunk_bytes"]),
            metadata={**config.get("metadata", {}), "writer": "process"},
            # Records reach the writer thread in batches: one wake-up per batch.
            batch_size=_CHILD_BATCH,
            batch_delay=_CHILD_BATCH_DELAY,
        )
        rec = SessionRecorder.open(config["directory"], config["room"], options)
    except Exception as exc:
        _emit({"event": "error", "room": room_id, "error": repr(exc)})
        return None
    _emit({"event": "ready", "room": room_id, "part": str(rec.part_path), "path": str(rec.path)})
    return rec


def _close_room(room_id: int, rec: SessionRecorder, end: float) -> bool:
    try:
        rec.close(end)
    except RecorderError as exc:
        statistics = asdict(rec.statistics())
        _emit({"event": "closed", "room": room_id, "statistics": statistics, "error": str(exc)})
        return False
    _emit({"event": "closed", "room": room_id, "statistics": asdict(rec.statistics())})
    return True


def _serve(fd: int) -> int:
    """Record every room the pipe opens until the pipe ends; the exit code."""
    rooms: dict[int, SessionRecorder] = {}
    failed = False
    buf = bytearray()
    frame_size = _FRAME.size
    while True:
        # Everything read goes to the rooms' writer threads at once (below), so
        # this process wakes only when the relay writes (every 0.25 s a room) or,
        # idle, once a second.
        ready, _, _ = select.select([fd], [], [], 1.0)
        if ready:
            chunk = os.read(fd, 1 << 20)
            if not chunk:
                break
            buf += chunk
            at, end = 0, len(buf)
            touched: set[int] = set()
            while end - at >= frame_size:
                kind, length, room_id = _FRAME.unpack_from(buf, at)
                start, nxt = at + frame_size, at + _HEAD.size + length
                if nxt > end:
                    break
                at = nxt
                if kind == _FRAME_OPEN:
                    rec = _open_room(room_id, json.loads(bytes(buf[start:nxt])))
                    if rec is not None:
                        rooms[room_id] = rec
                    continue
                if kind != _FRAME_BATCH or nxt < start:
                    # The stream itself is corrupt: nothing after this can be trusted.
                    _emit({"event": "error", "room": None, "error": f"bad frame {kind}"})
                    for rec in rooms.values():
                        rec.abandon()
                    return EXIT_ERROR
                rec = rooms.get(room_id)
                if rec is None:
                    continue  # a room whose file could not be opened, or that failed
                try:
                    stop = _record_batch(rec, buf, start, nxt)
                except (ValueError, IndexError, struct.error) as exc:
                    _emit({"event": "error", "room": room_id, "error": str(exc)})
                    rec.abandon()
                    del rooms[room_id]
                    failed = True
                    continue
                if stop is None:
                    touched.add(room_id)
                else:
                    del rooms[room_id]
                    touched.discard(room_id)
                    failed = not _close_room(room_id, rec, stop) or failed
            del buf[:at]
            for room_id in touched:
                rooms[room_id].hand_off()
        for room_id, rec in list(rooms.items()):
            if rec.failed:  # disk full: tell the relay now, not when the room closes
                _emit({"event": "error", "room": room_id, "error": rec.statistics().error})
                del rooms[room_id]
                failed = True
            else:
                rec.poll()
    if rooms:
        # The relay vanished (crash, SIGKILL): make what arrived durable, keep the .part files.
        for rec in rooms.values():
            rec.abandon()
            log.warning("recorder: the relay went away; %s kept for recovery", rec.part_path)
        return EXIT_RELAY_GONE
    return EXIT_ERROR if failed else EXIT_OK


def main(argv: list[str] | None = None) -> int:
    """The writer process: records the rooms the relay sends through standard input."""
    args = sys.argv[1:] if argv is None else argv
    if args:
        sys.stderr.write("usage: recorder.writerproc.main (started by the server; no arguments)\n")
        return 2
    logging.basicConfig(level=logging.WARNING, format="%(name)s: %(message)s")
    # Ctrl-C in a terminal signals the whole process group: the relay decides
    # when a session ends, by a room's stop message or by closing the pipe.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    # A background job beside a real-time relay: when the cores are contended the
    # scheduler runs the relay (and its clients) first; the writer has a second of
    # slack (the fsync schedule), and if it ever falls behind, losses are recorded.
    with contextlib.suppress(OSError):
        os.nice(_CHILD_NICE)
    return _serve(sys.stdin.buffer.fileno())


if __name__ == "__main__":
    sys.exit(main())
