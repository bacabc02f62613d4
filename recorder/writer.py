"""The session recorder: the relay hands it records, a writer thread puts them on disk.

The asyncio server calls the ``record_*`` methods from its event loop. They never
wait on the disk: each encodes its record (a few microseconds) and offers it to a
bounded ``queue.Queue``; a writer thread takes records from the queue and appends
them to an MCAP file (layout in :mod:`recorder.format`). When the queue is full
the record is lost, counted, and the loss itself is recorded: the next time the
queue has room, a ``drops`` record of kind ``recorder-queue-overflow`` goes in
first, with how many records (and poses) were lost and between which times.

Durability: the writer closes the current zstd chunk (``ChunkWriter.flush``) and
``os.fsync``\\ s the file at most ``flush_interval`` seconds (default 0.5 s) after
it wrote a record, so after a crash every record older than that (plus the queue
delay) is in a complete chunk on disk. The file is written as ``NAME.mcap.part``
and renamed to ``NAME.mcap`` by a clean :meth:`SessionRecorder.close`;
:func:`recorder.recovery.recover` turns a left-over ``.part`` into a complete file.

The recorder reads no clock for what it records: times are arguments (a JSON
record without one takes its ``"time"`` field, else ``clock()``, which the server
sets to its own clock). Only the flush schedule of the writer thread uses
``time.monotonic``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import queue
import threading
import time as _time
from collections.abc import Iterable, Mapping
from datetime import UTC, datetime
from pathlib import Path
from types import TracebackType
from typing import IO, Any, Final

from posecast.protocol.codec import Volume
from posecast.protocol.poses import PoseUpdate
from posecast.recorder.compact import (
    GROUP_SPAN_MAX,
    GROUP_UPDATES_MAX,
    CompactUpdate,
    compact_update,
    encode_group,
    newest_ns,
)
from posecast.recorder.files import (
    PART_SUFFIX,
    create_part,
    fsync_dir,
    safe_name,
    start_event,
    start_file,
)
from posecast.recorder.format import (
    SESSION_END_METADATA,
    encode_json,
    encode_pose,
    to_ns,
)
from posecast.recorder.mcapfile import MESSAGE_OVERHEAD, ChunkWriter
from posecast.recorder.options import (
    DEFAULT_CHUNK_BYTES,
    DEFAULT_FLUSH_INTERVAL,
    DEFAULT_QUEUE_SIZE,
    Clock,
    RecordOptions,
)
from posecast.recorder.tap import (
    _CHANNEL_IDS,
    _EVENTS,
    _POSES,
    RecorderError,
    RecorderStatistics,
    RecordTap,
    _Item,
    _Loss,
)

__all__ = [
    "DEFAULT_CHUNK_BYTES",
    "DEFAULT_FLUSH_INTERVAL",
    "DEFAULT_QUEUE_SIZE",
    "PART_SUFFIX",
    "RecordOptions",
    "SessionRecorder",
    "fsync_dir",
]

log = logging.getLogger("posecast.recorder")


class _Stop:
    def __init__(self, end_time: float) -> None:
        self.end_time = end_time


_HOLD: Final = object()
#: Tells the writer thread to make what it has durable and stop, keeping the ``.part``.
_ABANDON: Final = object()


class _Abandoned(Exception):
    pass


class SessionRecorder(RecordTap):
    """Records one room's session to ``NAME.mcap.part``; see the module docstring.

    Make one with :meth:`open`. ``record_*`` return ``True`` if the record was
    queued, ``False`` if it was lost (counted, and reported in the file).
    """

    def __init__(
        self,
        part_path: Path,
        final_path: Path,
        stream: IO[bytes],
        writer: ChunkWriter,
        *,
        clock: Clock,
        queue_size: int,
        flush_interval: float,
        chunk_records: int | None,
        chunk_bytes: int,
        batch_size: int = 1,
        batch_delay: float = 0.05,
    ) -> None:
        self.part_path = part_path
        self.path = final_path
        self._file = stream
        self._mcap = writer
        self._clock = clock
        # The bound holds about ``queue_size`` records whether they come alone or batched.
        self._queue: queue.Queue[object] = queue.Queue(
            maxsize=queue_size if batch_size <= 1 else max(2, queue_size // batch_size)
        )
        self._flush_interval = flush_interval
        self._chunk_records = chunk_records
        self._chunk_bytes = chunk_bytes
        self._lock = threading.Lock()
        self._loss = _Loss()
        self._closing = False
        self._closed = False
        self._error: BaseException | None = None
        self._resume = threading.Event()
        self._held = threading.Event()
        # Producer-side batching (the relay's thread only): records wait in a plain
        # list and go to the queue as one item, so the writer thread wakes (and
        # takes the GIL) once per batch, not once per record.
        self._batch_size = batch_size
        self._batch_delay = batch_delay
        self._batch: list[_Item] = []
        self._batch_since = 0.0
        # producer-side counters (under _lock)
        self._offered = 0
        self._queue_drops = 0
        self._queue_drop_poses = 0
        self._rejected = 0
        self._high_water = 0
        self._loss_records = 0
        # writer-side counters (only the writer thread writes them)
        self._sequence = 0
        self._pending = 0  # messages in the chunk being built
        self._written = 0
        self._poses_written = 0
        self._bytes = stream.tell()
        self._chunks = 0
        self._fsyncs = 0
        # compact updates of the open chunk (layout 2), the arrival span they cover
        self._group: list[CompactUpdate] = []
        self._group_span = (0.0, 0.0)
        self._compact_fallbacks = 0
        self._thread = threading.Thread(
            target=self._run, name=f"recorder:{final_path.name}", daemon=True
        )

    # -- opening ---------------------------------------------------------------------

    @classmethod
    def open(
        cls,
        directory: str | os.PathLike[str],
        room: str,
        options: RecordOptions | None = None,
        **keywords: Any,
    ) -> SessionRecorder:
        """Create ``directory/NAME.mcap.part``, write the session header, start the writer.

        ``options`` (or the same as keywords, replacing its fields): see
        :class:`RecordOptions`. ``batch_size`` > 1 hands records to the writer
        thread in batches (call :meth:`poll` regularly): far fewer thread
        wake-ups for a busy relay. The default hands over each record.
        """
        opts = RecordOptions.of(options, keywords)
        folder = Path(directory)
        folder.mkdir(parents=True, exist_ok=True)
        start_wall = opts.wall_clock()
        start = opts.clock()
        base = opts.name or (
            f"{safe_name(room)}-{datetime.fromtimestamp(start_wall, UTC):%Y%m%dT%H%M%SZ}"
        )
        part, final, stream = create_part(folder, base)
        try:
            writer = start_file(stream, room, opts, start, start_wall)
            rec = cls(
                part,
                final,
                stream,
                writer,
                clock=opts.clock,
                queue_size=opts.queue_size,
                flush_interval=opts.flush_interval,
                chunk_records=opts.chunk_records,
                chunk_bytes=opts.chunk_bytes,
                batch_size=1 if opts.batch_size is None else opts.batch_size,
                batch_delay=opts.batch_delay,
            )
            # Header, schemas, channels and the first chunk: durable from the start.
            start_ns = to_ns(start)
            rec._write((_EVENTS, start_ns, start_ns, encode_json(start_event(room, start)), 0))
            rec._sync()
            fsync_dir(folder)
        except BaseException:
            with contextlib.suppress(OSError):  # a full disk fails the close's flush too
                stream.close()
            part.unlink(missing_ok=True)  # no empty .part left behind
            raise
        rec._thread.start()
        log.info("recording room %r to %s", room, part)
        return rec

    # -- the relay's side: never blocks ----------------------------------------------

    def record_pose_update(
        self,
        user: int,
        arrival: float,
        update: PoseUpdate,
        codes: Mapping[int, list[int]] | None = None,
        volume: Volume | None = None,
    ) -> bool:
        """Queue one pose update of ``user`` as the relay decoded it (see :meth:`record_update`).

        ``codes`` (stream id -> codec codes, in the update's order) and ``volume``
        of a compact session: the update is recorded as its codes (layout 2).
        """
        if codes is not None and volume is not None:
            compact = compact_update(user, arrival, update, codes, volume)
            if compact is not None:
                n = len(compact.streams)
                return self._offer((_POSES, to_ns(arrival), newest_ns(compact), compact, n))
        return self.record_update(
            user,
            update.seq,
            arrival,
            update.streams,
            update.capture_times,
            update.poses,
            update.velocities,
        )

    def offer_encoded(
        self, channel: str, log_ns: int, publish_ns: int, data: bytes | CompactUpdate, poses: int
    ) -> bool:
        """Queue a record already encoded for ``channel`` (a topic of :data:`CHANNELS`)."""
        return self._offer((_CHANNEL_IDS[channel], log_ns, publish_ns, data, poses))

    def offer_encoded_many(
        self, channel: str, rows: Iterable[tuple[int, int, bytes | CompactUpdate, int]]
    ) -> bool:
        """Queue records already encoded for ``channel``: ``(log ns, publish ns, data, poses)``.

        As :meth:`offer_encoded` for each, in order, batched the same way.
        """
        cid = _CHANNEL_IDS[channel]
        items = [(cid, *row) for row in rows]
        if self._batch_size <= 1 or self._closing or self._error is not None:
            return all([self._offer(item) for item in items])
        size = self._batch_size
        while items:
            batch = self._batch
            if not batch:
                self._batch_since = _time.monotonic()
            room = size - len(batch)
            batch += items[:room]
            del items[:room]
            if len(batch) >= size:
                self._handoff()
        if self._batch and _time.monotonic() - self._batch_since >= self._batch_delay:
            self._handoff()
        return True

    def _take(self, topic: str, log_time: float, publish_ns: int, data: bytes, poses: int) -> bool:
        return self._offer((_CHANNEL_IDS[topic], to_ns(log_time), publish_ns, data, poses))

    def _count_rejected(self, n: int = 1) -> None:
        with self._lock:
            self._rejected += n

    def _offer(self, item: _Item) -> bool:
        if self._batch_size <= 1:
            return self._enqueue(item)
        if self._closing or self._error is not None:
            with self._lock:
                self._rejected += 1
            return False
        batch = self._batch
        if not batch:
            self._batch_since = _time.monotonic()
        batch.append(item)
        if (
            len(batch) >= self._batch_size
            or _time.monotonic() - self._batch_since >= self._batch_delay
        ):
            self._handoff()
        return True

    def poll(self) -> None:
        """Hand a waiting batch to the writer once it is ``batch_delay`` old.

        The relay calls this on every tick, so a quiet room's last records still
        reach the disk within ``batch_delay + flush_interval``.
        """
        if self._batch and _time.monotonic() - self._batch_since >= self._batch_delay:
            self._handoff()

    def _handoff(self) -> None:
        batch, self._batch = self._batch, []
        if batch:
            self._enqueue(batch)

    def hand_off(self) -> None:
        """Hand the waiting batch to the writer thread now (whatever its age)."""
        self._handoff()

    def _enqueue(self, item: _Item | list[_Item]) -> bool:
        """Queue a record (or a batch of them); on overflow count and remember the loss."""
        q = self._queue
        items = item if isinstance(item, list) else [item]
        with self._lock:
            if self._closing or self._error is not None:
                self._rejected += len(items)
                return False
            loss = self._loss
            try:
                if loss.records:
                    q.put_nowait(loss.item())
                    self._loss = _Loss()
                    self._loss_records += 1
                q.put_nowait(item)
            except queue.Full:
                for one in items:
                    self._loss.add(one)
                    self._queue_drops += 1
                    self._queue_drop_poses += one[4]
                return False
            self._offered += len(items)
            depth = len(q.queue)  # no lock: the deque's length is enough here
            if depth > self._high_water:
                self._high_water = depth
            return True

    # -- the writer thread -------------------------------------------------------------

    def _write(self, item: _Item) -> None:
        channel, log_ns, pub_ns, data, poses = item
        if isinstance(data, CompactUpdate):
            self._group_add(data)
        else:
            self._mcap.add_message(channel, log_ns, data, pub_ns, self._sequence)
            self._sequence += 1
            self._pending += 1
        self._written += 1
        self._poses_written += poses

    def _group_add(self, update: CompactUpdate) -> None:
        """Add a compact update to the open layout 2 group (written before the chunk closes)."""
        group = self._group
        if group:
            first = group[0]
            lo, hi = self._group_span
            lo, hi = min(lo, update.arrival), max(hi, update.arrival)
            if (
                update.volume != first.volume
                or update.velocity != first.velocity
                or hi - lo > GROUP_SPAN_MAX
                or len(group) >= GROUP_UPDATES_MAX
            ):
                self._group_write()
            else:
                self._group_span = (lo, hi)
        if not self._group:
            self._group_span = (update.arrival, update.arrival)
        self._group.append(update)

    def _group_write(self) -> None:
        """Write the open group as one layout 2 message (updates that do not code: layout 1)."""
        group, self._group = self._group, []
        if not group:
            return
        data, bad = encode_group(group)
        if data is not None:
            lo, hi = self._group_span
            self._mcap.add_message(_POSES, to_ns(lo), data, to_ns(hi), self._sequence)
            self._sequence += 1
            self._pending += 1
        for u in bad:
            r = u.record()
            raw = encode_pose(
                r.user, r.seq, r.arrival, r.streams, r.capture_times, r.poses, r.velocities
            )
            self._mcap.add_message(_POSES, to_ns(r.arrival), raw, newest_ns(u), self._sequence)
            self._sequence += 1
            self._pending += 1
        self._compact_fallbacks += len(bad)

    def _close_chunk(self) -> None:
        self._group_write()
        self._mcap.flush()
        if self._pending:
            self._chunks += 1
            self._pending = 0
        self._bytes = self._file.tell()

    def _sync(self) -> None:
        self._close_chunk()
        os.fsync(self._file.fileno())
        self._fsyncs += 1

    def _run(self) -> None:
        try:
            end_time = self._loop()
            self._finish(end_time)
        except _Abandoned:
            with contextlib.suppress(Exception):
                self._file.close()
        except OSError as exc:  # disk full, I/O error: keep the .part; the owner reports it
            self._error = exc
            log.warning("recorder for %s stopped: %s; the .part file is kept", self.path.name, exc)
            with contextlib.suppress(Exception):
                self._file.close()
        except BaseException as exc:
            self._error = exc
            log.exception("recorder for %s failed; the .part file is kept", self.path.name)
            with contextlib.suppress(Exception):
                self._file.close()

    def _loop(self) -> float:
        q = self._queue
        interval = self._flush_interval
        chunk_records = self._chunk_records or 0
        chunk_bytes = self._chunk_bytes
        monotonic = _time.monotonic
        deadline: float | None = None  # when the oldest unsynced record must be on disk
        in_chunk = 0
        chunk_size = 0
        while True:
            try:
                if deadline is None:
                    item = q.get()
                else:
                    item = q.get(timeout=max(0.0, deadline - monotonic()))
            except queue.Empty:
                item = None
            if isinstance(item, _Stop):
                return item.end_time
            if item is _ABANDON:
                self._sync()
                raise _Abandoned
            if item is _HOLD:
                self._held.set()
                self._resume.wait()
                self._held.clear()
            elif item is not None:
                recs: list[_Item] = item if isinstance(item, list) else [item]  # type: ignore[list-item]
                for rec in recs:
                    self._write(rec)
                    if deadline is None:
                        deadline = monotonic() + interval
                    in_chunk += 1
                    chunk_size += len(rec[3]) + MESSAGE_OVERHEAD
                    if (chunk_records and in_chunk >= chunk_records) or chunk_size >= chunk_bytes:
                        self._close_chunk()
                        in_chunk = chunk_size = 0
            if deadline is not None and monotonic() >= deadline:
                self._sync()
                deadline = None
                in_chunk = chunk_size = 0

    def _finish(self, end_time: float) -> None:
        self._close_chunk()  # every message before the session's end record
        if self._compact_fallbacks:
            log.warning(
                "recorder: %d compact updates of %s recorded as floats (layout 1): their"
                " codes did not decode to the relayed poses",
                self._compact_fallbacks,
                self.path.name,
            )
        self._mcap.add_metadata(
            SESSION_END_METADATA,
            {
                "end_time": repr(end_time),
                "records": str(self._written),
                "queue_drops": str(self._queue_drops),
            },
        )
        self._mcap.finish()
        self._file.flush()
        os.fsync(self._file.fileno())
        self._fsyncs += 1
        self._file.close()
        os.replace(self.part_path, self.path)
        fsync_dir(self.path.parent)
        self._bytes = self.path.stat().st_size

    # -- control -----------------------------------------------------------------------

    def hold(self, timeout: float = 10.0) -> None:
        """Pause the writer thread with the queue empty (tests: a stalled disk)."""
        self._resume.clear()
        if not self._put_blocking(_HOLD) or not self._held.wait(timeout):
            raise RecorderError("the writer thread did not pause")

    def release(self) -> None:
        """Let a writer paused by :meth:`hold` continue."""
        self._resume.set()

    def abandon(self) -> Path:
        """Make every queued record durable and stop, keeping ``NAME.mcap.part``.

        What a crash leaves, minus the loss: the writer closes its chunk and
        fsyncs, but writes no summary and does not rename. For a writer process
        whose relay vanished (it cannot know whether the session is over).
        """
        batch, self._batch = self._batch, []
        with self._lock:
            self._closing = True
            self._offered += len(batch)
        self.release()
        if batch:
            self._put_blocking(batch)
        self._put_blocking(_ABANDON)
        self._thread.join()
        self._closed = True
        return self.part_path

    def _put_blocking(self, item: object) -> bool:
        while self._thread.is_alive():
            try:
                self._queue.put(item, timeout=0.05)
                return True
            except queue.Full:
                continue
        return False

    def close(self, time: float | None = None) -> Path:
        """Write what is queued, the summary and indexes; rename to ``NAME.mcap``.

        Blocks (use :meth:`aclose` from the event loop). Raises
        :class:`RecorderError` if the writer thread failed, keeping the ``.part``.
        """
        if not self._closing and self._batch:
            batch, self._batch = self._batch, []
            self._put_blocking(batch)
            with self._lock:
                self._offered += len(batch)
        with self._lock:
            already = self._closing
            self._closing = True
            end = self._clock() if time is None else time
            loss, self._loss = self._loss, _Loss()
        if not already:
            self.release()
            if loss.records and self._put_blocking(loss.item()):
                with self._lock:
                    self._loss_records += 1
            self._put_blocking(_Stop(end))
        self._thread.join()
        self._closed = True
        if self._error is not None:
            raise RecorderError(
                f"recording failed ({self._error!r}); partial file kept at {self.part_path}"
            ) from self._error
        return self.path

    async def aclose(self, time: float | None = None) -> Path:
        """:meth:`close` in a worker thread, for the event loop."""
        return await asyncio.to_thread(self.close, time)

    def __enter__(self) -> SessionRecorder:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    @property
    def failed(self) -> bool:
        """True once the writer thread has failed (records are then rejected)."""
        return self._error is not None

    def statistics(self) -> RecorderStatistics:
        """A snapshot of the counters (any thread)."""
        with self._lock:
            return RecorderStatistics(
                records_offered=self._offered,
                records_written=self._written,
                poses_written=self._poses_written,
                queue_drops=self._queue_drops,
                queue_drop_poses=self._queue_drop_poses,
                loss_records=self._loss_records,
                rejected=self._rejected,
                bytes_written=self._bytes,
                chunks=self._chunks,
                fsyncs=self._fsyncs,
                queue_depth=self._queue.qsize(),
                queue_high_water=self._high_water,
                error=None if self._error is None else repr(self._error),
                closed=self._closed,
            )
