"""Session recorders whose MCAP writers run in one process of their own.

:class:`recorder.writer.SessionRecorder` encodes records on the relay's thread
and writes them from a thread of the relay's process, so every record costs the
relay some GIL time (encoding, MCAP framing, compression bookkeeping): about a
third of a CPU-bound relay's throughput in ``posecast bench relay --record``.
:class:`ProcessRecorder` has the same relay-facing methods but keeps almost all
of that work out of the relay's process, and :class:`RecorderHost` is the one
writer process a server shares between all its recorded rooms (a room opens in
milliseconds, and a server recording 100 rooms runs one writer, not 100):

- the relay hands over each pose update as it decoded it
  (:meth:`ProcessRecorder.record_pose_update`: sequence number, base time and
  entries' bytes behind a small header, plus the codes of a compact session;
  two list appends), and the few JSON records already encoded;
- every ``batch_delay`` s (the room ticks call :meth:`ProcessRecorder.poll`)
  each room's batch is joined into one blob (sooner, once it holds
  ``batch_size`` records), and all rooms' blobs are written into the host's
  non-blocking pipe (1 MiB) by the relay's own thread: one ``writev``, one
  wake-up of the child, whatever the number of rooms, and no thread hand-off (a
  feeder thread woken per batch cost the relay far more than the writing);
  what the pipe cannot take yet waits, bounded per room;
- the host's child process (:func:`recorder.writerproc.main`) reads the pipe,
  encodes each room's updates in groups of the same shape and records them with
  one :class:`SessionRecorder` per room (same file layout, chunking, fsync
  schedule, ``.part`` and rename).

Nothing is silent: when more than ``queue_size`` of a room's records wait (the
child or its disk cannot keep up and the pipe is full) a batch of that room is
lost, counted and the loss recorded in its file as a ``recorder-queue-overflow``
drops record, as the thread recorder does. If the relay dies, the child sees the
pipe close without the rooms' stops, makes what it received durable and leaves
every open room's ``.part`` for recovery. If the child dies, every room it was
recording fails (the relay goes on, the ``.part`` files stay) and the server
starts a new host for the rooms opened after that.

The pipe's layout and what the child answers: :mod:`recorder.pipe`.
"""

from __future__ import annotations

import collections
import contextlib
import fcntl
import itertools
import json
import logging
import os
import queue
import select
import struct
import subprocess
import sys
import threading
import time as _time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

from posecast.protocol.codec import Volume
from posecast.protocol.poses import PoseUpdate
from posecast.recorder.options import Clock, RecordOptions
from posecast.recorder.pipe import (
    _CHANNEL_INDEX,
    _COMPACT_EXTRA,
    _COMPACT_PACK,
    _FRAME_BATCH,
    _FRAME_OPEN,
    _KIND_COMPACT,
    _KIND_RECORD,
    _KIND_STOP,
    _KIND_UPDATE,
    _RECORD,
    _RECORD_EXTRA,
    _STOP,
    _UPDATE_EXTRA,
    _UPDATE_PACK,
    _VOLUME,
    _codes_struct,
    _frame,
    _room_config,
)
from posecast.recorder.tap import RecorderError, RecorderStatistics, RecordTap
from posecast.recorder.writer import SessionRecorder

from .format import DROPS_TOPIC, POSES_TOPIC, QUEUE_OVERFLOW_KIND, encode_json, to_ns

__all__ = ["ProcessRecorder", "RecorderHost", "RoomRecorder"]

log = logging.getLogger("posecast.recorder")

#: Seconds to wait for the child to open a room's file, and to finish it on close.
_START_TIMEOUT: Final = 60.0
_CLOSE_TIMEOUT: Final = 120.0
#: Linux's fcntl to resize a pipe (Python 3.11's fcntl lacks the name), and the size asked.
_F_SETPIPE_SZ: Final = getattr(fcntl, "F_SETPIPE_SZ", 1031)
_PIPE_BYTES: Final = 1 << 20
#: Blobs per writev (Linux's IOV_MAX is 1024).
_WRITEV_MAX: Final = 512
_CHILD_BOOT: Final = "import sys; from posecast.recorder.writerproc import main; sys.exit(main())"
#: Records a room hands over at a time unless its options say otherwise.
_BATCH_SIZE: Final = 256


class _Batch:
    """Records waiting on the relay's thread; what a loss of the batch would lose."""

    __slots__ = ("first", "last", "parts", "poses", "records", "topics", "updates")

    def __init__(self) -> None:
        self.parts: list[bytes] = []
        self.records = 0
        #: Pose updates among the records (the others are counted in ``topics``).
        self.updates = 0
        self.poses = 0
        self.first = 0.0
        self.last = 0.0
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


class RecorderHost:
    """One writer process that records any number of rooms; see the module docstring.

    Start it with :meth:`start` (blocks for the child's start-up: run it off the
    event loop), open rooms with :meth:`open_room`, and :meth:`close` it once its
    rooms are closed. Thread-safe: rooms open and close from worker threads while
    the relay's thread feeds the others.
    """

    def __init__(self, proc: subprocess.Popen[bytes]) -> None:
        self._proc = proc
        assert proc.stdin is not None and proc.stdout is not None
        # The pipe is written without blocking, from the relay's own thread.
        self._fd = proc.stdin.fileno()
        os.set_blocking(self._fd, False)
        with contextlib.suppress(OSError):  # a bigger pipe: seconds of records in flight
            fcntl.fcntl(self._fd, _F_SETPIPE_SZ, _PIPE_BYTES)
        #: Guards the pipe, the pending blobs and every room handle's counters.
        self.lock = threading.Lock()
        # [view, records, handle or None]: blobs not yet (fully) in the pipe, in order.
        self._pending: collections.deque[list[Any]] = collections.deque()
        self._held = False
        self._error: str | None = None
        self._ids = itertools.count(1)
        self._rooms: dict[int, ProcessRecorder] = {}
        self._replies: dict[int, queue.SimpleQueue[dict[str, Any] | None]] = {}
        self._eof = False
        self._closed = False
        # All rooms' batches go over together (one writev, one wake-up of the
        # child) every ``_flush_delay`` s: the shortest ``batch_delay`` of its rooms.
        self._flush_delay: float | None = None
        self._due = 0.0
        self._reader = threading.Thread(
            target=self._read_events, name=f"recorder-host-{proc.pid}", daemon=True
        )
        self._reader.start()

    @classmethod
    def start(cls) -> RecorderHost:
        """Start the writer process (a fraction of a second: its Python start-up)."""
        # The child runs the parent's interpreter, so it imports the same installed
        # posecast (a wheel, or an editable install's folder mapping).
        proc = subprocess.Popen(
            [sys.executable, "-c", _CHILD_BOOT], stdin=subprocess.PIPE, stdout=subprocess.PIPE
        )
        return cls(proc)

    # -- state -------------------------------------------------------------------------

    @property
    def pid(self) -> int:
        return self._proc.pid

    @property
    def alive(self) -> bool:
        """True while the child runs and the pipe to it works."""
        return self._error is None and not self._closed and self._proc.poll() is None

    @property
    def rooms(self) -> int:
        """Rooms opened on this host and not closed yet."""
        with self.lock:
            return len(self._rooms)

    # -- rooms -------------------------------------------------------------------------

    def open_room(
        self,
        directory: str | os.PathLike[str],
        room: str,
        options: RecordOptions | None = None,
        *,
        timeout: float = _START_TIMEOUT,
        **keywords: Any,
    ) -> ProcessRecorder:
        """Open room ``room``'s recording; return once the child created its ``.part``.

        Blocks for a round trip to the child (run it off the event loop).
        ``options`` (or the same as keywords, replacing its fields) as for
        :meth:`SessionRecorder.open`, but ``batch_size`` defaults to 256 and
        ``chunk_records`` is not taken. Raises :class:`RecorderError` if the
        child cannot open the file or is gone.
        """
        opts = RecordOptions.of(options, keywords)
        if opts.chunk_records is not None:
            raise TypeError("chunk_records is an option of the thread recorder only")
        room_id, replies = self._send_open(_room_config(directory, room, opts))
        try:
            ready = replies.get(timeout=timeout)
        except queue.Empty:
            ready = None
        if ready is None or ready.get("event") != "ready":
            with self.lock:
                self._replies.pop(room_id, None)
            detail = (ready or {}).get("error") or self._error or f"exit code {self._proc.poll()}"
            raise RecorderError(f"the recorder process did not start room {room!r}: {detail}")
        handle = ProcessRecorder(
            self,
            room_id,
            Path(ready["part"]),
            Path(ready["path"]),
            clock=opts.clock,
            queue_size=opts.queue_size,
            batch_size=_BATCH_SIZE if opts.batch_size is None else opts.batch_size,
        )
        with self.lock:
            self._rooms[room_id] = handle
            if self._flush_delay is None or opts.batch_delay < self._flush_delay:
                self._flush_delay = opts.batch_delay
        return handle

    def _send_open(
        self, config: dict[str, Any]
    ) -> tuple[int, queue.SimpleQueue[dict[str, Any] | None]]:
        """Send a room's ``OPEN`` frame; its id and where the child's replies arrive."""
        payload = json.dumps(config).encode()
        replies: queue.SimpleQueue[dict[str, Any] | None] = queue.SimpleQueue()
        with self.lock:
            if self._eof or self._closed or self._error is not None:
                raise RecorderError(
                    f"the recorder process is not running ({self._error or 'it ended'})"
                )
            room_id = next(self._ids)
            self._replies[room_id] = replies
            self._pending.append(
                [memoryview(_frame(_FRAME_OPEN, room_id, len(payload)) + payload), 0, None]
            )
        self.drain(block=True)
        return room_id, replies

    def _finished(self, room_id: int, timeout: float | None) -> dict[str, Any] | None:
        """The room's ``closed`` (or ``error``) reply, and forget the room.

        ``None`` if the child is gone or did not answer within ``timeout``
        (``None``: take only a reply already there).
        """
        with self.lock:
            replies = self._replies.get(room_id)
        try:
            if replies is None:
                return None
            if timeout is None:
                return replies.get_nowait()
            return replies.get(timeout=timeout)
        except queue.Empty:
            return None
        finally:
            with self.lock:
                self._replies.pop(room_id, None)
                self._rooms.pop(room_id, None)

    # -- the pipe: never blocks the relay ----------------------------------------------

    def _push(self, handle: ProcessRecorder | None, data: bytes, records: int) -> None:
        """Queue one blob (under :attr:`lock`)."""
        self._pending.append([memoryview(data), records, handle])
        if handle is not None:
            handle._pending_records += records

    def drain(self, block: bool = False, timeout: float = _CLOSE_TIMEOUT) -> None:
        """Write pending blobs into the pipe until it is full (or all, with ``block``).

        The lock is never held while waiting for the pipe, so the relay's thread
        goes on feeding other rooms while a closing room waits here. A child that
        takes nothing for ``timeout`` s while blocked on fails every room (their
        ``.part`` files stay): a stalled disk must not hang the server's shutdown.
        """
        deadline = _time.monotonic() + timeout
        while True:
            with self.lock:
                if self._held and not block:
                    return
                if self._write_locked():
                    return
                if not block:
                    return
                if _time.monotonic() >= deadline:
                    self._fail_locked(f"the recorder process took no records for {timeout:g} s")
                    return
            select.select([], [self._fd], [], 1.0)

    def _write_locked(self) -> bool:
        """Write what the pipe takes now; True once nothing is pending (or it failed)."""
        pending = self._pending
        while pending:
            views = [entry[0] for entry in itertools.islice(pending, _WRITEV_MAX)]
            try:
                written = os.writev(self._fd, views)
            except BlockingIOError:
                return False
            except OSError as exc:  # the child died: its .part files stay for recovery
                self._fail_locked(f"the recorder process stopped taking records ({exc})")
                return True
            while written:
                entry = pending[0]
                size = len(entry[0])
                if written < size:
                    entry[0] = entry[0][written:]
                    break
                written -= size
                pending.popleft()
                handle = entry[2]
                if handle is not None:
                    handle._pending_records -= entry[1]
        return True

    def flush(self, now: float) -> None:
        """Hand every room's waiting batch over and write them all at once (relay thread).

        The rooms' :meth:`ProcessRecorder.poll` calls it every flush delay.
        """
        with self.lock:
            self._due = now + (self._flush_delay or 0.05)
            for handle in self._rooms.values():
                if handle._batch.records and not handle._closing:
                    handle._handoff_locked()
        self.drain()

    def hold(self) -> None:
        """Stop feeding the child (tests: a stalled writer); records wait, up to each bound."""
        self._held = True

    def release(self) -> None:
        """Resume feeding after :meth:`hold`."""
        self._held = False
        self.drain()

    def check(self) -> None:
        """Fail every room if the child has exited (the rooms call it once a second)."""
        if self._error is None and not self._closed and self._proc.poll() is not None:
            with self.lock:
                self._fail_locked(f"the recorder process exited with code {self._proc.returncode}")

    def _fail_locked(self, message: str) -> None:
        if self._error is None:
            self._error = message
            log.error("%s; the rooms' .part files are kept for recovery", message)
        for handle in self._rooms.values():
            handle._fail_locked(message)
        for entry in self._pending:
            if entry[2] is not None:
                entry[2]._pending_records -= entry[1]
        self._pending.clear()

    # -- the child's replies -----------------------------------------------------------

    def _read_events(self) -> None:
        """Dispatch the child's JSON lines to the rooms waiting for them (a thread)."""
        stream = self._proc.stdout
        assert stream is not None
        try:
            for line in stream:
                try:
                    event: dict[str, Any] = json.loads(line)
                except ValueError:
                    log.error("recorder process: unreadable reply %r", line[:200])
                    continue
                self._dispatch(event)
        except (OSError, ValueError):  # the stream was closed under us
            pass
        with self.lock:
            self._eof = True
            for replies in self._replies.values():
                replies.put(None)
            if self._rooms:
                self._fail_locked("the recorder process ended while rooms were recording")

    def _dispatch(self, event: dict[str, Any]) -> None:
        room_id = event.get("room")
        with self.lock:
            if room_id is None:
                self._fail_locked(f"the recorder process failed: {event.get('error')}")
                return
            if event.get("event") == "error" and room_id in self._rooms:
                self._rooms[room_id]._fail_locked(str(event.get("error")))
            replies = self._replies.get(room_id)
        if replies is not None:
            replies.put(event)

    # -- closing -----------------------------------------------------------------------

    def close(self, timeout: float = _CLOSE_TIMEOUT) -> int:
        """Close the pipe and wait for the child; its exit code.

        Rooms still open are not finished: their ``.part`` files stay for
        recovery (close the rooms first).
        """
        if not self._closed:
            with contextlib.suppress(Exception):
                self.drain(block=self._error is None)
            self._closed = True
            with contextlib.suppress(OSError):
                assert self._proc.stdin is not None
                self._proc.stdin.close()
        try:
            code = self._proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            code = self._proc.wait()
        self._reader.join(timeout)
        with contextlib.suppress(OSError):
            assert self._proc.stdout is not None
            self._proc.stdout.close()
        return code

    def __enter__(self) -> RecorderHost:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class ProcessRecorder(RecordTap):
    """Records one room's session through a :class:`RecorderHost`; see the module docstring.

    :meth:`RecorderHost.open_room` makes one on a shared host; :meth:`open`
    starts a host of its own (closed with the room). The relay-facing methods
    match :class:`SessionRecorder` (``record_*`` return ``True`` if the record
    was taken, ``False`` if it was lost or refused, always counted).
    """

    def __init__(
        self,
        host: RecorderHost,
        room_id: int,
        part_path: Path,
        final_path: Path,
        *,
        clock: Clock,
        queue_size: int,
        batch_size: int,
    ) -> None:
        self._host = host
        self._id = room_id
        #: Set by :meth:`open`: this room's host is its own, closed with it.
        self._owns_host = False
        self.part_path = part_path
        self.path = final_path
        self._clock = clock
        self._batch_size = max(1, batch_size)
        # At most ``queue_size`` of this room's records wait for the pipe;
        # beyond that a batch is lost and the loss recorded.
        self._bound = max(1, queue_size)
        self._pending_records = 0
        self._lock = host.lock
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
        # the room volume of compact updates, and its bytes in the pipe
        self._volume: Volume | None = None
        self._box = b""

    @classmethod
    def open(
        cls,
        directory: str | os.PathLike[str],
        room: str,
        options: RecordOptions | None = None,
        *,
        timeout: float = _START_TIMEOUT,
        **keywords: Any,
    ) -> ProcessRecorder:
        """Start a writer process for this room alone; return once its ``.part`` exists.

        Blocks for the child's start-up (a fraction of a second; run it off the
        event loop). Arguments as for :meth:`RecorderHost.open_room`.
        """
        host = RecorderHost.start()
        try:
            rec = host.open_room(directory, room, options, timeout=timeout, **keywords)
        except BaseException:
            with contextlib.suppress(Exception):
                host.close(5.0)
            raise
        rec._owns_host = True
        return rec

    @property
    def host(self) -> RecorderHost:
        return self._host

    @property
    def _proc(self) -> subprocess.Popen[bytes]:
        """The writer process (shared with the host's other rooms)."""
        return self._host._proc

    # -- the relay's side: never blocks ----------------------------------------------

    def record_pose_update(
        self,
        user: int,
        arrival: float,
        update: PoseUpdate,
        codes: Mapping[int, list[int]] | None = None,
        volume: Volume | None = None,
    ) -> bool:
        """Take one pose update of ``user`` as the relay decoded it, arrived at ``arrival``.

        ``codes`` (stream id -> codec codes) and ``volume`` of a compact session:
        the writer records the update as its codes (layout 2).
        """
        if self._closing or self._error is not None:
            return self._refuse(1)
        entries = update.entries
        n = len(entries)
        body = entries.tobytes()
        b = self._batch
        if not b.records:
            b.first = arrival
        # Two appends, not ``+= (head, body)``: a tuple per update is a GC-tracked
        # allocation, and the relay's cyclic collections run per 700 of those.
        parts = b.parts
        seq, base = update.seq, update.base_time
        flat = b""
        if codes is not None and volume is not None and len(codes) == n:
            width = len(next(iter(codes.values()))) if n else 7
            with contextlib.suppress(struct.error):  # rows of unequal widths: not compact
                flat = _codes_struct(width * n).pack(*itertools.chain.from_iterable(codes.values()))
        if flat or (codes is not None and volume is not None and n == 0):
            assert volume is not None
            body += flat
            size = _COMPACT_EXTRA + len(body)
            if volume is not self._volume:
                self._volume, self._box = volume, _VOLUME.pack(*volume.lo, *volume.hi)
            head = _COMPACT_PACK(_KIND_COMPACT, size, user, n, arrival, seq, base, width)
            parts.append(head + self._box)
        else:
            size = _UPDATE_EXTRA + len(body)
            parts.append(_UPDATE_PACK(_KIND_UPDATE, size, user, n, arrival, seq, base))
        parts.append(body)
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
        """Call every tick: hands the rooms' batches over every flush delay."""
        host = self._host
        now = _time.monotonic()
        if now >= host._due:
            host.flush(now)
        elif host._pending:
            host.drain()
        if now - self._checked >= 1.0:
            self._checked = now
            if self._error is None and not self._closing:
                host.check()

    def _handoff(self) -> None:
        """Queue the waiting batch for the pipe and write what the pipe takes."""
        with self._lock:
            self._handoff_locked()
        self._host.drain()

    def _handoff_locked(self) -> None:
        batch, self._batch = self._batch, _Batch()
        if not batch.records:
            return
        parts = batch.parts
        batch.parts = []
        if self._error is not None:
            self._rejected += batch.records
            return
        if self._pending_records and self._pending_records + batch.records > self._bound:
            self._loss.add(batch, self._loss_topics)
            self._queue_drops += batch.records
            self._queue_drop_poses += batch.poses
            return
        self._send_locked(parts, batch.records)
        self._offered += batch.records
        self._high_water = max(self._high_water, self._pending_records)

    def _send_locked(self, parts: list[bytes], records: int) -> None:
        """Queue ``parts`` as one batch frame, behind the record of any loss not yet sent."""
        if self._loss.records:
            parts.insert(0, self._loss_message())
            self._loss_records += 1
            self._loss = _Loss()
            self._loss_topics = {}
        size = sum(map(len, parts))
        parts.insert(0, _frame(_FRAME_BATCH, self._id, size))
        self._host._push(self, b"".join(parts), records)

    def _loss_message(self) -> bytes:
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
            # A warning: the room's owner (the relay) reports the failure once, at ERROR.
            log.warning("recorder for %s failed: %s; the .part file is kept", self.path, message)

    # -- control -----------------------------------------------------------------------

    def hold(self, timeout: float = 10.0) -> None:
        """Stop feeding the host's child (tests: a stalled writer); records then wait."""
        del timeout
        self._host.hold()

    def release(self) -> None:
        """Resume feeding after :meth:`hold`."""
        self._host.release()

    def close(self, time: float | None = None) -> Path:
        """Send what is waiting and a stop; wait for the child to finish and rename.

        Blocks (use :meth:`aclose` from the event loop). Raises
        :class:`RecorderError` if the child failed, keeping the ``.part``.
        """
        host = self._host
        if not self._closing:
            end = self._clock() if time is None else time
            stop = _STOP.pack(_KIND_STOP, 8, end)
            with self._lock:
                # One step: a flush on the relay's thread cannot slip records behind the stop.
                self._handoff_locked()
                self._closing = True
                if self._error is None:
                    self._send_locked([stop], 0)
            host._held = False
            host.drain(block=True)
        # A failed room gets no reply; its entries on the host go all the same.
        closed = host._finished(self._id, _CLOSE_TIMEOUT if self._error is None else None)
        code = host.close() if self._owns_host else None
        self._closed = True
        if closed is not None and closed.get("event") == "closed":
            self._final = closed.get("statistics")
        final = self._final or {}
        if (
            closed is None
            or closed.get("event") != "closed"
            or closed.get("error")
            or final.get("error")
        ):
            detail = (closed or {}).get("error") or final.get("error") or self._error
            if code not in (None, 0):
                detail = f"{detail} (exit code {code})"
            self._fail(str(detail or "no reply from the recorder process"))
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
