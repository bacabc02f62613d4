"""The options of a room's recording, shared by the thread and the process recorders."""

from __future__ import annotations

import time as _time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, replace
from typing import Any

__all__ = [
    "DEFAULT_CHUNK_BYTES",
    "DEFAULT_FLUSH_INTERVAL",
    "DEFAULT_QUEUE_SIZE",
    "Clock",
    "RecordOptions",
]

#: Records the queue holds: 20 s of a 20-user room at 20 updates/s.
DEFAULT_QUEUE_SIZE = 8192
#: Seconds between closing a chunk and fsync-ing it, while records come in.
DEFAULT_FLUSH_INTERVAL = 0.5
#: A chunk is also closed once this many uncompressed bytes are in it.
DEFAULT_CHUNK_BYTES = 1 << 20

Clock = Callable[[], float]


@dataclass(frozen=True)
class RecordOptions:
    """How a room is recorded: the options of :meth:`SessionRecorder.open`,
    :meth:`recorder.host.ProcessRecorder.open` and
    :meth:`recorder.host.RecorderHost.open_room`.

    ``name`` is the file's ``NAME`` (default ``ROOM-YYYYmmddTHHMMSSZ``, made
    unique with ``-2``, ``-3``, ...). ``users`` are the members present at the
    start, as presence join dicts (``user``, ``name``, ``label``, ``streams``
    {name: id}, ``rate``). ``clock`` is the server clock the record times use,
    ``wall_clock`` the wall time of the start. At most ``queue_size`` records
    wait; a chunk is closed and fsynced ``flush_interval`` s after a record,
    and closed once it holds ``chunk_bytes`` (or ``chunk_records`` records, for
    tests; the thread recorder only). ``metadata`` adds string pairs to the
    ``posecast.session`` metadata. Records are handed over ``batch_size`` at a
    time, at most ``batch_delay`` s old (``None``: the recorder's default, each
    record for :class:`SessionRecorder`, 256 for the process recorder).
    """

    name: str | None = None
    users: Iterable[Mapping[str, Any]] = ()
    clock: Clock = _time.monotonic
    wall_clock: Clock = _time.time
    queue_size: int = DEFAULT_QUEUE_SIZE
    flush_interval: float = DEFAULT_FLUSH_INTERVAL
    chunk_records: int | None = None
    chunk_bytes: int = DEFAULT_CHUNK_BYTES
    metadata: Mapping[str, str] | None = None
    batch_size: int | None = None
    batch_delay: float = 0.05

    def __post_init__(self) -> None:
        if self.queue_size < 1:
            raise ValueError("queue_size must be at least 1")
        if not self.flush_interval > 0:
            raise ValueError("flush_interval must be positive")

    @classmethod
    def of(cls, options: RecordOptions | None, keywords: Mapping[str, Any]) -> RecordOptions:
        """``options`` (default: the defaults) with ``keywords`` replacing its fields."""
        if options is None:
            return cls(**keywords)
        return replace(options, **keywords) if keywords else options
