"""What :class:`server.core.RelayCore` tells its adapter to do (see its module docstring)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

if TYPE_CHECKING:
    from posecast.recorder import RoomRecorder

__all__ = ["Action", "Close", "FinishRecording", "Hold", "Rearm", "Reschedule", "Wake"]


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
    """Room ``room`` is gone: close ``recorder`` (blocking work: off the event loop)."""

    room: str
    recorder: RoomRecorder


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


Action = Wake | Close | Reschedule | Rearm | FinishRecording
