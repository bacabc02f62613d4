"""Publishers whose pose updates stopped while their connection stays up. Sans I/O.

A member whose connection stays up but whose pose updates stop for
``stall_after`` seconds (a frozen browser tab: its network process still answers
websocket pings, so keepalive never fires) is announced as a dropped one is:
peers get ``peer_stalled`` (the same message, no new field: its streams stay
frozen at their last pose, as a parked member's), and ``peer_resumed`` at its
next accepted update. A member that has never published is never silent. A
silent member whose connection then drops is parked without a second
``peer_stalled`` (``server.resume``); a resumed one is watched again from its
resume.

:class:`Silence` decides; whom to tell and how is the core's (the ``tell`` it is
given: every other member but spectators), as is re-arming its expiry timer.
"""

from __future__ import annotations

import heapq
from collections.abc import Callable

from posecast.protocol import PeerResumed, PeerStalled
from posecast.protocol.events import Message
from posecast.server.member import Member
from posecast.server.room import Room

__all__ = ["Silence", "Tell"]

#: Queue a notice about a member to the other members of its room.
Tell = Callable[[Room, Member, Message], None]


class Silence:
    """Publishers whose updates stopped while their connection stays up.

    Each publishing member has one deadline at most, at its last update plus
    ``after``: met with no newer update, its peers hear ``peer_stalled``;
    its next update brings ``peer_resumed``. An accepted update costs a store and
    two flag checks (a deadline is added only when a member starts publishing
    again), so the heap holds one entry per publisher, moved when it is met.
    """

    def __init__(self, after: float, tell: Tell, rearm: Callable[[], None]) -> None:
        #: The bound (s); 0: off.
        self.after = after
        self._tell, self._rearm = tell, rearm
        self._heap: list[tuple[float, int, Room, Member]] = []
        self._seq = 0
        #: Members announced stalled for silence, and announced back.
        self.stalls = self.resumes = 0

    def updated(self, room: Room, member: Member, now: float) -> None:
        """``member`` of ``room`` had an update accepted at ``now``."""
        member.last_update = now
        if member.silent:
            member.silent = False
            self.resumes += 1
            self._tell(room, member, PeerResumed(user=member.user))
        if not member.watched and self.after > 0:
            self._push(now + self.after, room, member)
            self._rearm()

    def watch(self, room: Room, member: Member, now: float) -> None:
        """Watch a publisher from ``now`` on afresh (it resumed after a drop)."""
        if member.last_update is not None and self.after > 0:
            member.last_update = now
            if not member.watched:
                self._push(now + self.after, room, member)

    def _push(self, at: float, room: Room, member: Member) -> None:
        member.watched = True
        self._seq += 1
        heapq.heappush(self._heap, (at, self._seq, room, member))

    def next(self) -> float | None:
        """When the earliest publisher may have been silent for ``after`` (None: none)."""
        return self._heap[0][0] if self._heap else None

    def expire(self, now: float) -> None:
        """Announce every publisher silent for ``after`` at ``now``; re-arm the others."""
        heap = self._heap
        while heap and heap[0][0] <= now:
            _, _, room, member = heapq.heappop(heap)
            member.watched = False
            if room.members.get(member.user) is not member or member.parked:
                continue  # it left, or dropped (parked: its peers heard that)
            last = member.last_update
            assert last is not None
            if now - last >= self.after - 1e-9:
                member.silent = True
                self.stalls += 1
                self._tell(room, member, PeerStalled(user=member.user))
            else:
                self._push(last + self.after, room, member)
