"""A session recorder whose MCAP writer runs in its own process.

:class:`recorder.writer.SessionRecorder` encodes records on the relay's thread
and writes them from a thread of the relay's process, so every record costs the
relay some GIL time (encoding, MCAP framing, compression bookkeeping): about a
third of a CPU-bound relay's throughput in ``posecast bench relay --record``.
:class:`ProcessRecorder` has the same relay-facing methods but keeps almost all
of that work out of the relay's process:

- the relay hands over each pose update as it decoded it
  (:meth:`ProcessRecorder.record_pose_update`: the update's sequence number,
  base time and entries' bytes, packed behind a small header; two list
  appends), and the few JSON records (presence, events, drops) already encoded;
- at most every ``batch_delay`` s (the room tick calls :meth:`poll`) or every
  ``batch_size`` records the batch is joined into one blob and written into a
  non-blocking pipe (1 MiB) by the relay's own thread: one system call, no
  thread hand-off (a feeder thread woken per batch cost the relay far more
  than the writing); what the pipe cannot take yet waits, bounded;
- a child process (:func:`main` here) reads the pipe, encodes the updates in
  groups of the same shape and records them with a :class:`SessionRecorder` of its own (same
  file layout, chunking, fsync schedule, ``.part`` and rename).

Nothing is silent: when more than ``queue_size`` records wait (the child or its
disk cannot keep up and the pipe is full) a batch is lost, counted and the loss
recorded in the file as a ``recorder-queue-overflow`` drops record, as the
thread recorder does. If the
relay dies, the child sees the pipe close without a stop message, makes what it
received durable and leaves the ``.part`` for recovery.

Pipe messages (little-endian): ``u8 kind, u32 length, payload``:
``UPDATE``: ``u16 user, u32 poses, f64 arrival, u64 seq, f64 base time`` + the
update's entries (:data:`protocol.UPDATE_DTYPE` or, for the velocity variant,
:data:`protocol.UPDATE_VELOCITY_DTYPE` records: their size tells which);
``RECORD``: ``u8 channel index, i64 log ns, i64 publish ns, u32 poses`` + data;
``STOP``: ``f64 end time``. The child's standard output carries JSON lines:
``{"event": "ready", "part": ..., "path": ...}`` once the file is open and
``{"event": "closed", "statistics": {...}}`` at the end.
"""

from __future__ import annotations

import collections
import contextlib
import fcntl
import json
import logging
import os
import select
import signal
import struct
import subprocess
import sys
import threading
import time as _time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import IO, Any, Final

import numpy as np

from protocol.poses import UPDATE_DTYPE, UPDATE_VELOCITY_DTYPE, PoseUpdate
from recorder.format import (
    CHANNELS,
    DROPS_TOPIC,
    POSES_TOPIC,
    QUEUE_OVERFLOW_KIND,
    encode_json,
    encode_pose_batch,
    to_ns,
    to_ns_many,
)
from recorder.writer import (
    DEFAULT_CHUNK_BYTES,
    DEFAULT_FLUSH_INTERVAL,
    DEFAULT_QUEUE_SIZE,
    RecorderError,
    RecorderStatistics,
    RecordTap,
    SessionRecorder,
)

__all__ = ["ProcessRecorder", "RoomRecorder"]

log = logging.getLogger("posecast.recorder")

_KIND_UPDATE: Final = 1
_KIND_RECORD: Final = 2
_KIND_STOP: Final = 3
_HEAD: Final = struct.Struct("<BI")
# head + user, poses, arrival, seq, base time (the entries' size tells their layout)
_UPDATE: Final = struct.Struct("<BIHIdQd")
_UPDATE_EXTRA: Final = _UPDATE.size - _HEAD.size
_UPDATE_PACK: Final = _UPDATE.pack
_PLAIN_ITEM: Final = UPDATE_DTYPE.itemsize
_VELOCITY_ITEM: Final = UPDATE_VELOCITY_DTYPE.itemsize
_RECORD: Final = struct.Struct("<BIBqqI")  # head + channel, log ns, publish ns, poses
_RECORD_EXTRA: Final = _RECORD.size - _HEAD.size
_STOP: Final = struct.Struct("<BId")
_TOPICS: Final = [spec.topic for spec in CHANNELS]
_CHANNEL_INDEX: Final = {topic: i for i, topic in enumerate(_TOPICS)}
#: Seconds to wait for the child to open the file, and to finish it on close.
_START_TIMEOUT: Final = 60.0
_CLOSE_TIMEOUT: Final = 120.0
#: Linux's fcntl to resize a pipe (Python 3.11's fcntl lacks the name), and the size asked.
_F_SETPIPE_SZ: Final = getattr(fcntl, "F_SETPIPE_SZ", 1031)
_PIPE_BYTES: Final = 1 << 20
_CHILD_BOOT: Final = "import sys; from recorder.process import main; sys.exit(main())"
#: The child's own hand-off to its writer thread: records per batch, seconds at most.
_CHILD_BATCH: Final = 256
_CHILD_BATCH_DELAY: Final = 0.05
#: Niceness the writer process adds to its own (a lower CPU priority than the relay's).
_CHILD_NICE: Final = 10

Clock = Callable[[], float]


class _Batch:
    """Records waiting on the relay's thread; what a loss of the batch would lose."""

    __slots__ = ("first", "last", "parts", "poses", "records", "since", "topics", "updates")

    def __init__(self) -> None:
        self.parts: list[bytes] = []
        self.records = 0
        #: Pose updates among the records (the others are counted in ``topics``).
        self.updates = 0
        self.poses = 0
        self.first = 0.0
        self.last = 0.0
        self.since = 0.0
        self.topics: dict[str, int] = {}


@dataclass
class _Loss:
    records: int = 0
    poses: int = 0
    first: float = 0.0
    last: float = 0.0

    def add(self, batch: _Batch, topics: dict[str, int]) -> None:
        if self.records == 0 or batch.first < self.first:
            self.first = batch.first
        self.last = max(self.last, batch.last)
        self.records += batch.records
        self.poses += batch.poses
        if batch.updates:
            topics[POSES_TOPIC] = topics.get(POSES_TOPIC, 0) + batch.updates
        for k, v in batch.topics.items():
            topics[k] = topics.get(k, 0) + v


class ProcessRecorder(RecordTap):
    """Records one room's session from a child process; see the module docstring.

    Make one with :meth:`open`; the relay-facing methods match
    :class:`SessionRecorder` (``record_*`` return ``True`` if the record was
    taken, ``False`` if it was lost or refused, always counted).
    """

    def __init__(
        self,
        proc: subprocess.Popen[bytes],
        part_path: Path,
        final_path: Path,
        *,
        clock: Clock,
        queue_size: int,
        batch_size: int,
        batch_delay: float,
    ) -> None:
        self._proc = proc
        self.part_path = part_path
        self.path = final_path
        self._clock = clock
        self._batch_size = max(1, batch_size)
        self._batch_delay = batch_delay
        # The pipe is written without blocking, from the relay's own thread: no
        # thread hand-off (which cost the relay more than the writing itself).
        # What the pipe cannot take now waits in ``_pending``, at most
        # ``queue_size`` records; beyond that a batch is lost and the loss recorded.
        assert proc.stdin is not None
        self._fd = proc.stdin.fileno()
        os.set_blocking(self._fd, False)
        with contextlib.suppress(OSError):  # a bigger pipe: seconds of records in flight
            fcntl.fcntl(self._fd, _F_SETPIPE_SZ, _PIPE_BYTES)
        self._bound = max(1, queue_size)
        self._pending: collections.deque[list[Any]] = collections.deque()  # [view, records]
        self._pending_records = 0
        self._held = False
        self._lock = threading.Lock()
        self._batch = _Batch()
        self._loss = _Loss()
        self._loss_topics: dict[str, int] = {}
        self._closing = False
        self._closed = False
        self._error: str | None = None
        self._final: dict[str, Any] | None = None
        self._offered = 0
        self._queue_drops = 0
        self._queue_drop_poses = 0
        self._loss_records = 0
        self._rejected = 0
        self._high_water = 0
        self._checked = _time.monotonic()

    # -- opening ---------------------------------------------------------------------

    @classmethod
    def open(
        cls,
        directory: str | os.PathLike[str],
        room: str,
        *,
        name: str | None = None,
        users: Iterable[Mapping[str, Any]] = (),
        clock: Clock = _time.monotonic,
        wall_clock: Clock = _time.time,
        queue_size: int = DEFAULT_QUEUE_SIZE,
        flush_interval: float = DEFAULT_FLUSH_INTERVAL,
        chunk_bytes: int = DEFAULT_CHUNK_BYTES,
        metadata: Mapping[str, str] | None = None,
        batch_size: int = 256,
        batch_delay: float = 0.05,
    ) -> ProcessRecorder:
        """Start the writer process; return once it has created ``NAME.mcap.part``.

        Blocks for the child's start-up (a fraction of a second; run it off the
        event loop). Arguments as for :meth:`SessionRecorder.open`; the child's
        own queue is ``queue_size`` records as well.
        """
        if queue_size < 1:
            raise ValueError("queue_size must be at least 1")
        if not flush_interval > 0:
            raise ValueError("flush_interval must be positive")
        config = {
            "directory": str(Path(directory).resolve()),
            "room": room,
            "name": name,
            "users": [dict(u) for u in users],
            "start": clock(),
            "start_wall": wall_clock(),
            "queue_size": queue_size,
            "flush_interval": flush_interval,
            "chunk_bytes": chunk_bytes,
            "metadata": dict(metadata or {}),
        }
        env = dict(os.environ)
        # The child imports this package the way the parent did.
        root = str(Path(__file__).resolve().parent.parent)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
        proc = subprocess.Popen(
            [sys.executable, "-c", _CHILD_BOOT, json.dumps(config)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            env=env,
        )
        assert proc.stdout is not None
        try:
            ready = _read_event(proc, proc.stdout, _START_TIMEOUT)
            if ready is None or ready.get("event") != "ready":
                raise RecorderError(
                    f"the recorder process did not start (exit code {proc.poll()}): "
                    f"{(ready or {}).get('error', 'see its log')}"
                )
        except BaseException:
            with contextlib.suppress(Exception):
                proc.kill()
                proc.wait(5)
            for pipe in (proc.stdin, proc.stdout):
                with contextlib.suppress(Exception):
                    if pipe is not None:
                        pipe.close()
            raise
        return cls(
            proc,
            Path(ready["part"]),
            Path(ready["path"]),
            clock=clock,
            queue_size=queue_size,
            batch_size=batch_size,
            batch_delay=batch_delay,
        )

    # -- the relay's side: never blocks ----------------------------------------------

    def record_pose_update(self, user: int, arrival: float, update: PoseUpdate) -> bool:
        """Take one pose update of ``user`` as the relay decoded it, arrived at ``arrival``."""
        if self._closing or self._error is not None:
            return self._refuse(1)
        entries = update.entries
        n = len(entries)
        body = entries.tobytes()
        b = self._batch
        if not b.records:
            b.since = _time.monotonic()
            b.first = arrival
        b.parts += (
            _UPDATE_PACK(
                _KIND_UPDATE,
                _UPDATE_EXTRA + len(body),
                user,
                n,
                arrival,
                update.seq,
                update.base_time,
            ),
            body,
        )
        b.records += 1
        b.updates += 1
        b.poses += n
        b.last = arrival
        if b.records >= self._batch_size:
            self._handoff()
        return True

    def _take(self, topic: str, log_time: float, publish_ns: int, data: bytes, poses: int) -> bool:
        if self._closing or self._error is not None:
            return self._refuse(1)
        b = self._batch
        if not b.records:
            b.since = _time.monotonic()
            b.first = b.last = log_time
        head = _RECORD.pack(
            _KIND_RECORD,
            _RECORD_EXTRA + len(data),
            _CHANNEL_INDEX[topic],
            to_ns(log_time),
            publish_ns,
            poses,
        )
        b.parts += (head, data)
        b.records += 1
        b.poses += poses
        b.first = min(b.first, log_time)
        b.last = max(b.last, log_time)
        b.topics[topic] = b.topics.get(topic, 0) + 1
        if b.records >= self._batch_size:
            self._handoff()
        return True

    def _count_rejected(self, n: int = 1) -> None:
        self._refuse(n)

    def _refuse(self, n: int) -> bool:
        with self._lock:
            self._rejected += n
        return False

    def poll(self) -> None:
        """Hand the waiting batch over once it is ``batch_delay`` old (call every tick)."""
        b = self._batch
        now = _time.monotonic()
        if b.records and now - b.since >= self._batch_delay:
            self._handoff()
        elif self._pending:
            self._drain()
        if now - self._checked >= 1.0:
            self._checked = now
            if self._error is None and not self._closing and self._proc.poll() is not None:
                self._fail(f"the recorder process exited with code {self._proc.returncode}")

    def _handoff(self) -> None:
        batch, self._batch = self._batch, _Batch()
        if batch.records:
            self._enqueue(batch)

    def _enqueue(self, batch: _Batch) -> bool:
        blob = b"".join(batch.parts)
        batch.parts = []
        with self._lock:
            if self._error is not None:
                self._rejected += batch.records
                return False
            if self._pending and self._pending_records + batch.records > self._bound:
                self._loss.add(batch, self._loss_topics)
                self._queue_drops += batch.records
                self._queue_drop_poses += batch.poses
                return False
            if self._loss.records:
                self._push(self._loss_blob(), 0)
                self._loss_records += 1
                self._loss = _Loss()
                self._loss_topics = {}
            self._push(blob, batch.records)
            self._offered += batch.records
            self._high_water = max(self._high_water, self._pending_records)
        self._drain()
        return True

    def _push(self, data: bytes, records: int) -> None:
        self._pending.append([memoryview(data), records])
        self._pending_records += records

    def _drain(self, block: bool = False) -> None:
        """Write pending blobs into the pipe until it is full (or all, with ``block``)."""
        with self._lock:
            if self._held and not block:
                return
            pending = self._pending
            while pending:
                entry = pending[0]
                view: memoryview = entry[0]
                try:
                    written = os.write(self._fd, view)
                except BlockingIOError:
                    if not block:
                        return
                    select.select([], [self._fd], [], 1.0)
                    continue
                except OSError as exc:  # the child died: its .part stays for recovery
                    self._fail_locked(f"the recorder process stopped taking records ({exc})")
                    pending.clear()
                    self._pending_records = 0
                    return
                if written < len(view):
                    entry[0] = view[written:]
                    continue
                pending.popleft()
                self._pending_records -= entry[1]

    def _loss_blob(self) -> bytes:
        loss = self._loss
        record = {
            "kind": QUEUE_OVERFLOW_KIND,
            "count": loss.records,
            "poses": loss.poses,
            "topics": dict(self._loss_topics),
            "first_time": loss.first,
            "last_time": loss.last,
            "time": loss.last,
        }
        data = encode_json(record)
        ns = to_ns(loss.last)
        head = _RECORD.pack(
            _KIND_RECORD, _RECORD_EXTRA + len(data), _CHANNEL_INDEX[DROPS_TOPIC], ns, ns, 0
        )
        return head + data

    def _fail(self, message: str) -> None:
        with self._lock:
            self._fail_locked(message)

    def _fail_locked(self, message: str) -> None:
        if self._error is None:
            self._error = message
            log.error("recorder for %s failed: %s; the .part file is kept", self.path, message)

    # -- control -----------------------------------------------------------------------

    def hold(self, timeout: float = 10.0) -> None:
        """Stop feeding the child (tests: a stalled writer); records then wait, up to the bound."""
        del timeout
        self._held = True

    def release(self) -> None:
        """Resume feeding after :meth:`hold`."""
        self._held = False
        self._drain()

    def close(self, time: float | None = None) -> Path:
        """Send what is waiting and a stop; wait for the child to finish and rename.

        Blocks (use :meth:`aclose` from the event loop). Raises
        :class:`RecorderError` if the child failed, keeping the ``.part``.
        """
        if not self._closing:
            end = self._clock() if time is None else time
            self._handoff()
            with self._lock:
                self._closing = True
                if self._loss.records:
                    self._push(self._loss_blob(), 0)
                    self._loss_records += 1
                    self._loss = _Loss()
                self._push(_STOP.pack(_KIND_STOP, 8, end), 0)
            self._held = False
            self._drain(block=True)
        proc = self._proc
        assert proc.stdin is not None and proc.stdout is not None
        with contextlib.suppress(OSError):
            proc.stdin.close()
        closed = _read_event(proc, proc.stdout, _CLOSE_TIMEOUT)
        try:
            code = proc.wait(_CLOSE_TIMEOUT)
        except subprocess.TimeoutExpired:
            proc.kill()
            code = proc.wait()
        with contextlib.suppress(OSError):
            proc.stdout.close()
        self._closed = True
        if closed is not None and closed.get("event") == "closed":
            self._final = closed.get("statistics")
        if code != 0 or self._final is None or (self._final or {}).get("error"):
            detail = (closed or {}).get("error") or (self._final or {}).get("error") or self._error
            self._fail(f"exit code {code}: {detail}")
            raise RecorderError(
                f"recording failed ({self._error}); partial file kept at {self.part_path}"
            )
        return self.path

    async def aclose(self, time: float | None = None) -> Path:
        """:meth:`close` in a worker thread, for the event loop."""
        import asyncio

        return await asyncio.to_thread(self.close, time)

    def __enter__(self) -> ProcessRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def failed(self) -> bool:
        """True once the child process or the pipe to it failed."""
        return self._error is not None

    def statistics(self) -> RecorderStatistics:
        """A snapshot of the counters; the child's own are filled in once it closed."""
        final = self._final or {}
        path = self.path if self._closed and self.path.exists() else self.part_path
        try:
            size = path.stat().st_size
        except OSError:
            size = 0
        with self._lock:
            return RecorderStatistics(
                records_offered=self._offered,
                records_written=int(final.get("records_written", 0)),
                poses_written=int(final.get("poses_written", 0)),
                queue_drops=self._queue_drops + int(final.get("queue_drops", 0)),
                queue_drop_poses=self._queue_drop_poses + int(final.get("queue_drop_poses", 0)),
                loss_records=self._loss_records + int(final.get("loss_records", 0)),
                rejected=self._rejected + int(final.get("rejected", 0)),
                bytes_written=size,
                chunks=int(final.get("chunks", 0)),
                fsyncs=int(final.get("fsyncs", 0)),
                queue_depth=self._pending_records,
                queue_high_water=self._high_water,
                error=self._error,
                closed=self._closed,
            )


#: What a server room records through: either recorder has the relay-facing methods.
RoomRecorder = SessionRecorder | ProcessRecorder


def _read_event(
    proc: subprocess.Popen[bytes], stream: IO[bytes], timeout: float
) -> dict[str, Any] | None:
    """The child's next JSON line, or ``None`` if it closed its output or timed out."""
    deadline = _time.monotonic() + timeout
    fd = stream.fileno()
    buf = b""
    while True:
        left = deadline - _time.monotonic()
        if left <= 0:
            return None
        ready, _, _ = select.select([fd], [], [], min(left, 0.5))
        if not ready:
            if proc.poll() is not None:
                return None
            continue
        chunk = os.read(fd, 65536)
        if not chunk:
            return None
        buf += chunk
        if b"\n" in buf:
            line = buf.split(b"\n", 1)[0]
            try:
                event: dict[str, Any] = json.loads(line)
            except ValueError:
                return None
            return event


# -- the child process -------------------------------------------------------------------


def _emit(event: Mapping[str, Any]) -> None:
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


def _pump(rec: SessionRecorder, fd: int) -> float | None:
    """Record what comes through the pipe; the stop's end time, or ``None`` at its end."""
    buf = bytearray()
    head_size = _HEAD.size
    update_at, record_at = _UPDATE.size, _RECORD.size
    updates: list[_Update] = []
    while True:
        # Everything read goes to the writer thread at once (below), so this
        # process wakes only when the relay writes (every 0.25 s a room) or,
        # idle, once a second.
        ready, _, _ = select.select([fd], [], [], 1.0)
        if ready:
            chunk = os.read(fd, 1 << 20)
            if not chunk:
                return None
            buf += chunk
            at = 0
            end = len(buf)
            while end - at >= head_size:
                kind, length = _HEAD.unpack_from(buf, at)
                stop = at + head_size + length
                if stop > end:
                    break
                if kind == _KIND_UPDATE:
                    head = _UPDATE.unpack_from(buf, at)
                    updates.append((*head[2:], bytes(buf[at + update_at : stop])))
                else:
                    # Keep the file's record order: the updates before this record first.
                    if updates:
                        _record_updates(rec, updates)
                        updates = []
                    if kind == _KIND_RECORD:
                        _k, _n, channel, log_ns, pub_ns, poses = _RECORD.unpack_from(buf, at)
                        data = bytes(buf[at + record_at : stop])
                        rec.offer_encoded(_TOPICS[channel], log_ns, pub_ns, data, poses)
                    elif kind == _KIND_STOP:
                        return float(_STOP.unpack_from(buf, at)[2])
                    else:
                        raise ValueError(f"unknown pipe message kind {kind}")
                at = stop
            del buf[:at]
            if updates:
                _record_updates(rec, updates)
                updates = []
            rec.hand_off()
        rec.poll()


def _child(config: Mapping[str, Any]) -> int:
    """Read the pipe until a stop (finish the file) or its end (keep the ``.part``)."""
    # Ctrl-C in a terminal signals the whole process group: the relay decides
    # when the session ends, by a stop message or by closing the pipe.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    # A background job beside a real-time relay: when the cores are contended the
    # scheduler runs the relay (and its clients) first; the writer has a second of
    # slack (the fsync schedule), and if it ever falls behind, losses are recorded.
    with contextlib.suppress(OSError):
        os.nice(_CHILD_NICE)
    start, start_wall = float(config["start"]), float(config["start_wall"])
    try:
        rec = SessionRecorder.open(
            config["directory"],
            config["room"],
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
    except Exception as exc:
        _emit({"event": "error", "error": repr(exc)})
        return 1
    _emit({"event": "ready", "part": str(rec.part_path), "path": str(rec.path)})
    try:
        end = _pump(rec, sys.stdin.buffer.fileno())
    except ValueError as exc:
        _emit({"event": "error", "error": str(exc)})
        rec.abandon()
        return 1
    if end is None:
        # The relay vanished (crash, SIGKILL): make what arrived durable, keep the .part.
        rec.abandon()
        log.warning("recorder: the relay went away; %s kept for recovery", rec.part_path)
        return 2
    try:
        rec.close(end)
    except RecorderError as exc:
        _emit({"event": "closed", "statistics": asdict(rec.statistics()), "error": str(exc)})
        return 1
    _emit({"event": "closed", "statistics": asdict(rec.statistics())})
    return 0


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        sys.stderr.write("usage: recorder.process.main CONFIG_JSON (started by the server)\n")
        return 2
    logging.basicConfig(level=logging.WARNING, format="%(name)s: %(message)s")
    return _child(json.loads(args[0]))


if __name__ == "__main__":
    sys.exit(main())
