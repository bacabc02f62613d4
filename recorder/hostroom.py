"""One room recorded through a writer process: the relay's side of a hosted recording.

A :class:`HostedRoom` takes the room's records on the relay's thread and never
blocks it:

- each pose update as the relay decoded it (:meth:`HostedRoom.record_pose_update`:
  sequence number, base time and entries' bytes behind a small header, plus the
  codes of a compact session; two list appends), and the few JSON records
  already encoded (:class:`recorder.tap.RecordTap`'s ``record_*``);
- the room's records wait in one batch, handed to its host as one blob once it
  holds ``batch_size`` records, or when the host flushes every room (every
  ``batch_delay`` s, from :meth:`HostedRoom.poll` on the room ticks);
- when more than ``queue_size`` of the room's records wait for the host's pipe
  (the child or its disk cannot keep up and the pipe is full) the batch is lost,
  counted and the loss recorded in the room's file as a
  ``recorder-queue-overflow`` drops record, as the thread recorder does;
- :meth:`HostedRoom.close` sends what waits and a stop, and waits for the
  child's reply (the ``.part`` renamed, or an error and the ``.part`` kept).

The room needs of its host only the surface :class:`Host` names (the pipe, its
lock, the child's replies); :class:`recorder.host.RecorderHost` is that host, and
it sees a room only through :meth:`HostedRoom.flush_locked` and
:meth:`HostedRoom.fail_locked`. So this module imports nothing of the host's.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import struct
import subprocess
import threading
import time as _time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final, Generic, Protocol, Self, TypeVar

from posecast.protocol.codec import Volume
from posecast.protocol.poses import PoseUpdate
from posecast.recorder.format import (
    DROPS_TOPIC,
    POSES_TOPIC,
    QUEUE_OVERFLOW_KIND,
    encode_json,
    to_ns,
)
from posecast.recorder.options import Clock
from posecast.recorder.pipe import (
    _CHANNEL_INDEX,
    _COMPACT_EXTRA,
    _COMPACT_PACK,
    _FRAME_BATCH,
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
)
from posecast.recorder.tap import RecorderError, RecorderStatistics, RecordTap

__all__ = ["CLOSE_TIMEOUT", "Host", "HostedRoom"]

log = logging.getLogger("posecast.recorder")

#: Seconds to wait for the child to finish a room's file on close.
CLOSE_TIMEOUT: Final = 120.0


class Host(Protocol):
    """What a room needs of the writer process it records through.

    :attr:`lock` guards the host's pipe and every room's batch and counters: the
    methods named ``*_locked`` (here and on the room) run under it.
    """

    lock: threading.Lock

    @property
    def process(self) -> subprocess.Popen[bytes]: ...

    def push_locked(self, room_id: int | None, data: bytes, records: int) -> None:
        """Queue one blob of ``records`` records of room ``room_id`` for the pipe."""

    def waiting_locked(self, room_id: int) -> int:
        """Records of room ``room_id`` queued and not yet (fully) in the pipe."""
        ...

    def poll(self, now: float) -> None:
        """Flush every room if the flush delay has passed, else write what waits."""

    def drain(self, block: bool = False, timeout: float = CLOSE_TIMEOUT) -> None:
        """Write what waits into the pipe (until it is full, or all with ``block``)."""

    def check(self) -> None:
        """Fail every room if the child has exited."""

    def hold(self) -> None:
        """Stop feeding the child."""

    def release(self) -> None:
        """Resume feeding after :meth:`hold`."""

    def finished(self, room_id: int, timeout: float | None) -> dict[str, Any] | None:
        """The room's ``closed`` (or ``error``) reply, and forget the room."""
        ...

    def close(self, timeout: float = CLOSE_TIMEOUT) -> int:
        """Close the pipe and wait for the child; its exit code."""
        ...


H = TypeVar("H", bound=Host)


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


class HostedRoom(RecordTap, Generic[H]):
    """Records one room's session through a :class:`Host`; see the module docstring.

    The relay-facing methods match :class:`recorder.writer.SessionRecorder`
    (``record_*`` return ``True`` if the record was taken, ``False`` if it was
    lost or refused, always counted).
    """

    def __init__(
        self,
        host: H,
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
        #: Set by :meth:`own_host`: this room's host is its own, closed with it.
        self._owns_host = False
        self.part_path = part_path
        self.path = final_path
        self._clock = clock
        self._batch_size = max(1, batch_size)
        # At most ``queue_size`` of this room's records wait for the pipe;
        # beyond that a batch is lost and the loss recorded.
        self._bound = max(1, queue_size)
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

    @property
    def room_id(self) -> int:
        """The room's id on its host's pipe."""
        return self._id

    def own_host(self) -> None:
        """Close the host with this room (a host started for this room alone)."""
        self._owns_host = True

    @property
    def host(self) -> H:
        """The writer process's host (shared with the host's other rooms)."""
        return self._host

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
        now = _time.monotonic()
        self._host.poll(now)
        if now - self._checked >= 1.0:
            self._checked = now
            if self._error is None and not self._closing:
                self._host.check()

    # -- hand-offs to the host (under its lock) ------------------------------------------

    def flush_locked(self) -> None:
        """Hand the waiting batch over, if there is one and the room is not closing."""
        if self._batch.records and not self._closing:
            self._handoff_locked()

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
        waiting = self._host.waiting_locked(self._id)
        if waiting and waiting + batch.records > self._bound:
            self._loss.add(batch, self._loss_topics)
            self._queue_drops += batch.records
            self._queue_drop_poses += batch.poses
            return
        self._send_locked(parts, batch.records)
        self._offered += batch.records
        self._high_water = max(self._high_water, self._host.waiting_locked(self._id))

    def _send_locked(self, parts: list[bytes], records: int) -> None:
        """Queue ``parts`` as one batch frame, behind the record of any loss not yet sent."""
        if self._loss.records:
            parts.insert(0, self._loss_message())
            self._loss_records += 1
            self._loss = _Loss()
            self._loss_topics = {}
        size = sum(map(len, parts))
        parts.insert(0, _frame(_FRAME_BATCH, self._id, size))
        self._host.push_locked(self._id, b"".join(parts), records)

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
            self.fail_locked(message)

    def fail_locked(self, message: str) -> None:
        """The room's recording failed (its ``.part`` stays); it takes no more records."""
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
            host.release()
            host.drain(block=True)
        # A failed room gets no reply; its entries on the host go all the same.
        closed = host.finished(self._id, CLOSE_TIMEOUT if self._error is None else None)
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

    def __enter__(self) -> Self:
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
                queue_depth=self._host.waiting_locked(self._id),
                queue_high_water=self._high_water,
                error=self._error,
                closed=self._closed,
            )
