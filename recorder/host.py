"""Session recorders whose MCAP writers run in one process of their own.

:class:`recorder.writer.SessionRecorder` encodes records on the relay's thread
and writes them from a thread of the relay's process, so every record costs the
relay some GIL time (encoding, MCAP framing, compression bookkeeping): about a
third of a CPU-bound relay's throughput in ``posecast bench relay --record``.
:class:`ProcessRecorder` has the same relay-facing methods but keeps almost all
of that work out of the relay's process, and :class:`RecorderHost` is the one
writer process a server shares between all its recorded rooms (a room opens in
milliseconds, and a server recording 100 rooms runs one writer, not 100).

Three modules, one job each:

- here, :class:`RecorderHost`: the writer process and the relay's end of its
  pipe. Every ``batch_delay`` s (the room ticks call :meth:`ProcessRecorder.poll`)
  it has each room hand its batch over as one blob, and writes all rooms'
  blobs into its non-blocking pipe (1 MiB) from the relay's own thread: one
  ``writev``, one wake-up of the child, whatever the number of rooms, and no
  thread hand-off (a feeder thread woken per batch cost the relay far more than
  the writing); what the pipe cannot take yet waits, counted per room. A thread
  reads the child's replies and hands them to the rooms waiting for them.
- :mod:`recorder.hostroom`: one room's side (:class:`ProcessRecorder`'s
  methods): its records batched on the relay's thread, the bound on what waits
  (a batch beyond it is lost, counted and recorded as a
  ``recorder-queue-overflow`` drops record, as the thread recorder does), its
  counters and its close. It sees its host through the
  :class:`recorder.hostroom.Host` protocol and imports nothing of this module;
  the host sees a room through its ``flush_locked`` and ``fail_locked``.
- :func:`recorder.writerproc.main`, the child: reads the pipe, encodes each
  room's updates in groups of the same shape and records them with one
  :class:`SessionRecorder` per room (same file layout, chunking, fsync
  schedule, ``.part`` and rename).

If the relay dies, the child sees the pipe close without the rooms' stops, makes
what it received durable and leaves every open room's ``.part`` for recovery. If
the child dies, every room it was recording fails (the relay goes on, the
``.part`` files stay) and the server starts a new host for the rooms opened
after that.

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
import subprocess
import sys
import threading
import time as _time
from pathlib import Path
from typing import Any, Final

from posecast.recorder.hostroom import CLOSE_TIMEOUT, HostedRoom
from posecast.recorder.options import RecordOptions
from posecast.recorder.pipe import _FRAME_OPEN, _frame, _room_config
from posecast.recorder.tap import RecorderError
from posecast.recorder.writer import SessionRecorder

__all__ = ["ProcessRecorder", "RecorderHost", "RoomRecorder"]

log = logging.getLogger("posecast.recorder")

#: Seconds to wait for the child to open a room's file (finishing it: CLOSE_TIMEOUT).
_START_TIMEOUT: Final = 60.0
_CLOSE_TIMEOUT: Final = CLOSE_TIMEOUT
#: Linux's fcntl to resize a pipe (Python 3.11's fcntl lacks the name), and the size asked.
_F_SETPIPE_SZ: Final = getattr(fcntl, "F_SETPIPE_SZ", 1031)
_PIPE_BYTES: Final = 1 << 20
#: Blobs per writev (Linux's IOV_MAX is 1024).
_WRITEV_MAX: Final = 512
_CHILD_BOOT: Final = "import sys; from posecast.recorder.writerproc import main; sys.exit(main())"
#: Records a room hands over at a time unless its options say otherwise.
_BATCH_SIZE: Final = 256


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
        #: Guards the pipe, the pending blobs and every room's batch and counters.
        self.lock = threading.Lock()
        # [view, records, room id or None]: blobs not yet (fully) in the pipe, in order.
        self._pending: collections.deque[list[Any]] = collections.deque()
        # room id -> its records in those blobs
        self._waiting: dict[int, int] = {}
        self._held = False
        self._error: str | None = None
        self._ids = itertools.count(1)
        self._rooms: dict[int, HostedRoom[RecorderHost]] = {}
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
    def process(self) -> subprocess.Popen[bytes]:
        """The writer process (its pipe is written through this host only)."""
        return self._proc

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

    def finished(self, room_id: int, timeout: float | None) -> dict[str, Any] | None:
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
                self._waiting.pop(room_id, None)

    # -- the pipe: never blocks the relay ----------------------------------------------

    def push_locked(self, room_id: int | None, data: bytes, records: int) -> None:
        """Queue one blob of ``records`` records of room ``room_id`` (under :attr:`lock`)."""
        self._pending.append([memoryview(data), records, room_id])
        if room_id is not None:
            self._waiting[room_id] = self._waiting.get(room_id, 0) + records

    def waiting_locked(self, room_id: int) -> int:
        """Records of room ``room_id`` queued, not yet (fully) in the pipe (under :attr:`lock`)."""
        return self._waiting.get(room_id, 0)

    def _written_locked(self, room_id: int | None, records: int) -> None:
        """A blob of room ``room_id`` is in the pipe (or dropped with a failed pipe)."""
        if room_id is not None and room_id in self._waiting:
            self._waiting[room_id] -= records

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
                self._written_locked(entry[2], entry[1])
        return True

    def flush(self, now: float) -> None:
        """Hand every room's waiting batch over and write them all at once (relay thread).

        The rooms' :meth:`ProcessRecorder.poll` calls it every flush delay.
        """
        with self.lock:
            self._due = now + (self._flush_delay or 0.05)
            for room in self._rooms.values():
                room.flush_locked()
        self.drain()

    def poll(self, now: float) -> None:
        """Flush every room once the flush delay has passed, else write what waits."""
        if now >= self._due:
            self.flush(now)
        elif self._pending:
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
        for room in self._rooms.values():
            room.fail_locked(message)
        for entry in self._pending:
            self._written_locked(entry[2], entry[1])
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
                self._rooms[room_id].fail_locked(str(event.get("error")))
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


class ProcessRecorder(HostedRoom[RecorderHost]):
    """Records one room's session through a :class:`RecorderHost`; see the module docstring.

    :meth:`RecorderHost.open_room` makes one on a shared host; :meth:`open`
    starts a host of its own (closed with the room). The relay-facing methods
    (:class:`recorder.hostroom.HostedRoom`'s) match :class:`SessionRecorder`
    (``record_*`` return ``True`` if the record was taken, ``False`` if it was
    lost or refused, always counted).
    """

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
        rec.own_host()
        return rec


#: What a server room records through: either recorder has the relay-facing methods.
RoomRecorder = SessionRecorder | ProcessRecorder
