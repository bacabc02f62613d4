"""What :class:`server.core.RelayCore` tells its adapter to do (see its module docstring),
log lines included: the core and its parts import no ``logging``."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

if TYPE_CHECKING:
    from posecast.protocol import PoseUpdate
    from posecast.protocol.codec import Volume

__all__ = [
    "Action",
    "Close",
    "FinishRecording",
    "Hold",
    "Log",
    "PollRecording",
    "Rearm",
    "Record",
    "RecordPose",
    "Reschedule",
    "Wake",
]


@dataclass(frozen=True, slots=True)
class Wake:
    """Connection ``conn`` has frames to write: ``take(conn, now)``."""

    conn: int


@dataclass(frozen=True, slots=True)
class Close:
    """Close connection ``conn`` (after its queued messages) with ``code`` and ``reason``."""

    conn: int
    code: int
    reason: str


@dataclass(frozen=True, slots=True)
class Reschedule:
    """The earliest tick may have changed: consult ``next_deadline()`` again."""


@dataclass(frozen=True, slots=True)
class Rearm:
    """A connection deadline was added or moved: consult ``next_expiry()`` again."""


@dataclass(frozen=True, slots=True)
class FinishRecording:
    """Room ``room`` is gone: close its recording (blocking work: off the event loop)."""

    room: str


@dataclass(frozen=True, slots=True)
class Record:
    """Write ``record`` at ``now`` on room ``room``'s recording: a ``presence`` (join,
    leave, rate), ``event`` (a user event, an object's change) or ``drop`` record."""

    room: str
    topic: Literal["presence", "event", "drop"]
    record: dict[str, Any]
    now: float


@dataclass(frozen=True, slots=True)
class RecordPose:
    """Record ``user``'s pose ``update`` (``codes``: a compact update's codec codes,
    quantised in ``volume``) at ``now`` on room ``room``'s recording."""

    room: str
    user: int
    now: float
    update: PoseUpdate
    codes: dict[int, list[int]] | None
    volume: Volume


@dataclass(frozen=True, slots=True)
class PollRecording:
    """Room ``room`` ticked: its recording may hand its batch to the writer now."""

    room: str


@dataclass(frozen=True, slots=True)
class Hold:
    """Connection ``conn``'s event (and what it sent after it) waits for the adapter:
    ``open`` room ``room``'s recording, ``claim`` room ``room`` in the cluster, or
    ``resume``: find the member resumable with ``token`` in the cluster. Once done,
    the adapter hands the same event to ``handle`` (see ``RelayCore.hold``)."""

    conn: int
    kind: Literal["open", "claim", "resume"]
    room: str = ""
    token: str | None = None


@dataclass(frozen=True, slots=True)
class Log:
    """Log ``message % args`` at ``level`` (``logging``'s numbers: ``INFO``, ``WARNING``, ``ERROR``)
    on the relay's logger, ``posecast.server``; ``error``: the exception whose
    traceback goes with it (a room's tick that failed)."""

    level: int
    message: str
    args: tuple[object, ...] = ()
    error: BaseException | None = None


#: The levels a :class:`Log` uses (``logging.INFO``, ``logging.ERROR``: the core
#: imports no ``logging``).
INFO = 20
WARNING = 30
ERROR = 40

Action = (
    Wake
    | Close
    | Reschedule
    | Rearm
    | FinishRecording
    | Hold
    | Record
    | RecordPose
    | PollRecording
    | Log
)
