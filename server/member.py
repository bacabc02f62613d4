"""A room's member as the room sees it, the outbox it is written through, and ids.

A :class:`Member` is one joined user of a room (``server/room.py``): its streams,
its rate grid, what it last received, and its per-member state of the rules that
act on it (silence, parking, auto rates, per-peer rates). Its connection is an
:class:`Outbox`: one latest-wins pose slot (an unsent snapshot replaced by a newer
one is a skip) and a bounded queue of reliable messages (overflow is reported to
the caller, which closes the connection). :class:`IdAllocator` hands out the u16
user and stream ids. Nothing here touches a socket or reads a clock.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from posecast.server.config import DEFAULT_EVENT_QUEUE
from posecast.server.presence import Presence
from posecast.server.view_rates import ViewState

if TYPE_CHECKING:
    from posecast.server.rates import LinkRate

__all__ = ["IdAllocator", "Member", "Outbox"]


class IdAllocator:
    """u16 ids in ``[start, limit)``, reused oldest-freed first so that a just-freed id
    is not handed out again. Ids outside the range (a cluster node's members that came
    through another node, see ``server.cluster``) are never taken back."""

    def __init__(self, limit: int = 1 << 16, start: int = 0) -> None:
        self._start = self._next = start
        self._limit = limit
        self._free: deque[int] = deque()

    def take(self) -> int:
        if self._next < self._limit:
            self._next += 1
            return self._next - 1
        if not self._free:
            raise RuntimeError("no free ids left")
        return self._free.popleft()

    def reserve(self, ident: int) -> bool:
        """Take ``ident`` itself (a member restored on another cluster node keeps its
        ids); False if it is taken already. Ids outside the range are not tracked."""
        if not self._start <= ident < self._limit:
            return True
        if ident >= self._next:
            self._free.extend(range(self._next, ident))
            self._next = ident + 1
            return True
        if ident in self._free:
            self._free.remove(ident)
            return True
        return False

    def give_back(self, ident: int) -> None:
        if self._start <= ident < self._next:
            self._free.append(ident)

    def __len__(self) -> int:
        return self._next - self._start - len(self._free)


class Outbox:
    """What one connection still has to write: one pose slot and a bounded queue.

    ``buffered`` is the socket's unsent bytes as the adapter last reported them
    (``RelayCore.buffered``: a number, never a call into the adapter); above
    ``congested_bytes`` the room gives the connection no new snapshot (a skip) until
    it drains.
    """

    def __init__(
        self,
        max_events: int = DEFAULT_EVENT_QUEUE,
        buffered: int = 0,
        congested_bytes: int = 64 * 1024,
    ) -> None:
        self.pose: bytes | None = None
        self.events: deque[bytes] = deque()
        self.max_events = max_events
        self.buffered = buffered
        self.congested_bytes = congested_bytes
        #: The connection it is written to (None: none, e.g. a member restored
        #: parked): whoever offers it a frame returns ``Wake(conn)`` to the adapter.
        self.conn: int | None = None
        self.skips = 0
        self.snapshots_offered = 0

    def congested(self) -> bool:
        return self.buffered > self.congested_bytes

    def offer_snapshot(self, data: bytes) -> None:
        """Latest wins: a snapshot still waiting is replaced (and counted as a skip)."""
        if self.pose is not None:
            self.skips += 1
        self.pose = data
        self.snapshots_offered += 1

    def offer_event(self, data: bytes) -> bool:
        """Queue a reliable message; ``False`` if the queue is full (caller closes)."""
        if len(self.events) >= self.max_events:
            return False
        self.events.append(data)
        return True

    def take(self) -> bytes | None:
        """Next frame to write: queued events first, in order, then the snapshot."""
        return self.take_with_kind()[0]

    def take_with_kind(self) -> tuple[bytes | None, bool]:
        """Like :meth:`take`, and whether the frame is the snapshot."""
        if self.events:
            return self.events.popleft(), False
        data, self.pose = self.pose, None
        return data, data is not None


@dataclass
class Member:
    """A joined user as its room sees it."""

    user: int
    name: str
    streams: dict[str, int]
    rate: float
    outbox: Outbox
    label: str | None = None
    #: The rate the subscriber asked for; ``rate`` may be lower (an emulated link's cap).
    asked_rate: float = 0.0
    next_due: float = 0.0
    #: Store version covered by the newest snapshot offered to this member.
    last_version: int = 0
    #: Store version covered by the snapshots its writer has taken: the base of
    #: the next delta. It lags ``last_version`` while a snapshot waits unsent.
    delivered_version: int = 0
    snapshots: int = 0
    snapshot_bytes: int = 0
    poses_sent: int = 0
    congestion_skips: int = 0
    updates_in: int = 0
    #: Receives velocity-variant snapshots (``Join.wants_velocities``).
    velocities: bool = False
    #: Its updates carry velocities (``Join.sends_velocities``).
    sends_velocities: bool = False
    #: Receives compact snapshots (``Join.codec == "compact"``), without its own
    #: streams unless ``echo``.
    compact: bool = False
    echo: bool = False
    #: The key grid slot of its last key snapshot (-1: due one now), and whether
    #: its newest snapshot was a key.
    key_slot: int = -1
    key_sent: bool = False
    #: Its connection dropped and it waits to be resumed (``server.resume``): no
    #: snapshots meanwhile, its streams stay at their last pose.
    parked: bool = False
    #: Server time of its last accepted pose update (None: it has published none),
    #: whether its peers were told it stalled for having stopped publishing, and
    #: whether a silence deadline watches it (``server.silence.Silence``).
    last_update: float | None = None
    silent: bool = False
    watched: bool = False
    #: Its rate controller, if it joined with ``rate="auto"`` (``server.rates``).
    link_rate: LinkRate | None = None
    #: Presence notices it has not been sent yet (``server.presence``).
    presence: Presence = field(default_factory=Presence)
    #: Its per-peer schedule, if it joined with ``budget_deg`` (``server.view_rates``).
    view: ViewState | None = None

    def undelivered(self) -> None:
        """Its newest snapshot never reaches it (an emulated link lost or skipped
        it): the next is coded against what it holds, and is a key if that was."""
        self.last_version = self.delivered_version
        if self.view is not None:
            self.view.last = dict(self.view.delivered)
        if self.key_sent:
            self.key_slot = -1
