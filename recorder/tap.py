"""The relay-facing side of a recorder: the record_* encoders, channel ids, loss, counters."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Final

import numpy as np
from numpy.typing import ArrayLike

from posecast.protocol.errors import PosecastError
from posecast.recorder.compact import CompactUpdate
from posecast.recorder.format import (
    CHANNELS,
    DROPS_TOPIC,
    EVENTS_TOPIC,
    POSES_TOPIC,
    PRESENCE_TOPIC,
    QUEUE_OVERFLOW_KIND,
    encode_json,
    encode_pose,
    to_ns,
)
from posecast.recorder.options import Clock

__all__ = ["RecordTap", "RecorderError", "RecorderStatistics"]

log = logging.getLogger("posecast.recorder")

_CHANNEL_IDS: Final = {spec.topic: i + 1 for i, spec in enumerate(CHANNELS)}
_POSES = _CHANNEL_IDS[POSES_TOPIC]
_EVENTS = _CHANNEL_IDS[EVENTS_TOPIC]
_PRESENCE = _CHANNEL_IDS[PRESENCE_TOPIC]
_DROPS = _CHANNEL_IDS[DROPS_TOPIC]

# A queued record: channel id, log time ns, publish time ns, data, poses in it. A
# compact update waits in the writer thread and is written in a layout 2 message.
_Item = tuple[int, int, int, bytes | CompactUpdate, int]


class RecorderError(PosecastError, RuntimeError):
    """The recorder failed (disk full, I/O error); the ``.part`` file is kept."""


@dataclass(frozen=True)
class RecorderStatistics:
    """Counters of a :class:`SessionRecorder`; ``bytes_written`` is the file size so far."""

    records_offered: int
    """Records the ``record_*`` methods accepted into the queue."""
    records_written: int
    """Records written to the file (including the recorder's own drops records; each
    update of a layout 2 message counts)."""
    poses_written: int
    queue_drops: int
    """Records lost because the queue was full (each is also in a drops record)."""
    queue_drop_poses: int
    loss_records: int
    """Drops records queued to report queue overflows."""
    rejected: int
    """Records that could not be encoded or came after close (logged, counted)."""
    bytes_written: int
    chunks: int
    fsyncs: int
    queue_depth: int
    queue_high_water: int
    error: str | None
    closed: bool


class _Loss:
    """Records lost to a full queue since the last loss record was queued."""

    __slots__ = ("first", "last", "poses", "records", "topics")

    def __init__(self) -> None:
        self.records = 0
        self.poses = 0
        self.first = 0
        self.last = 0
        self.topics: dict[str, int] = {}

    def add(self, item: _Item) -> None:
        channel, log_ns, _pub, _data, poses = item
        if self.records == 0 or log_ns < self.first:
            self.first = log_ns
        self.last = max(self.last, log_ns)
        self.records += 1
        self.poses += poses
        topic = CHANNELS[channel - 1].topic
        self.topics[topic] = self.topics.get(topic, 0) + 1

    def item(self) -> _Item:
        record = {
            "kind": QUEUE_OVERFLOW_KIND,
            "count": self.records,
            "poses": self.poses,
            "topics": self.topics,
            "first_time": self.first / 1e9,
            "last_time": self.last / 1e9,
            "time": self.last / 1e9,
        }
        return (_DROPS, self.last, self.last, encode_json(record), 0)


class RecordTap:
    """The relay-facing ``record_*`` methods both recorders share.

    They encode a record on the caller's thread and hand it to ``_take``, which
    never blocks: it returns ``True`` if the record was taken, ``False`` if it
    was lost or refused (always counted). Subclasses set ``_clock`` (the server
    clock, for a JSON record without a time) and implement ``_take`` and
    ``_count_rejected``.
    """

    _clock: Clock

    def _take(self, topic: str, log_time: float, publish_ns: int, data: bytes, poses: int) -> bool:
        raise NotImplementedError

    def _count_rejected(self, n: int = 1) -> None:
        raise NotImplementedError

    def record_update(
        self,
        user: int,
        seq: int,
        arrival: float,
        streams: ArrayLike,
        capture_times: ArrayLike,
        poses: ArrayLike,
        velocities: ArrayLike | None = None,
    ) -> bool:
        """Take one pose update: stream ids (n,), capture times (n,), poses (n, 7).

        ``velocities`` (n, 6), if the update carried them, are recorded too.
        """
        try:
            caps = np.asarray(capture_times, dtype="<f8")
            data = encode_pose(user, seq, arrival, streams, caps, poses, velocities)
        except (TypeError, ValueError) as exc:
            return self._reject(POSES_TOPIC, exc)
        # publish_time: the newest capture time of the update
        newest = max(caps.tolist()) if len(caps) else arrival
        return self._take(POSES_TOPIC, arrival, to_ns(newest), data, len(caps))

    def record_event(self, event: Mapping[str, Any], time: float | None = None) -> bool:
        """Take an event (grab, release, button, ...) as JSON on ``events``."""
        return self._json(EVENTS_TOPIC, event, time)

    def record_presence(self, presence: Mapping[str, Any], time: float | None = None) -> bool:
        """Take a join / leave / rate record on ``presence``.

        Join: ``{"kind": "join", "user", "name", "label", "streams": {name: id},
        "rate"}``; leave: ``{"kind": "leave", "user", "reason"}``; rate change:
        ``{"kind": "rate", "user", "rate"}``.
        """
        return self._json(PRESENCE_TOPIC, presence, time)

    def record_drop(self, drop: Mapping[str, Any], time: float | None = None) -> bool:
        """Take a server-side drop or skip, e.g. ``{"kind": "flood", "user": 3, "count": 1}``."""
        return self._json(DROPS_TOPIC, drop, time)

    def _json(self, topic: str, record: Mapping[str, Any], time: float | None) -> bool:
        try:
            if time is None:
                t = record.get("time")
                time = float(t) if isinstance(t, int | float) else self._clock()
            data = encode_json(record)
        except (TypeError, ValueError) as exc:
            return self._reject(topic, exc)
        return self._take(topic, time, to_ns(time), data, 0)

    def _reject(self, topic: str, exc: Exception) -> bool:
        return self.refuse(topic, str(exc))

    def refuse(self, topic: str, reason: str) -> bool:
        """Count a ``topic`` record that cannot be recorded, and log why; returns ``False``."""
        self._count_rejected()
        log.warning("recorder: %s record not recorded: %s", topic, reason)
        return False
