"""Presence notices (``peer_joined`` / ``peer_left``), batched per room tick.

A member no longer hears of every join and leave the moment it happens: each
member keeps a :class:`Presence`, the changes it has not been told yet, net per
user, and the room sends them at its next tick, before the tick's snapshot
(``server.rooms`` calls :func:`flusher`'s hook). So a peer that reconnects 57
times a second costs each member at most one batch per tick, not 114 messages:

- a peer that joined and left within one tick is never announced;
- repeated changes collapse to the net state: a member that knew the peer hears
  one ``peer_left``, or ``peer_left`` then ``peer_joined`` if it came back as a
  new member (new streams); one that did not know it hears one ``peer_joined``;
- per user the order is kept (its ``peer_left`` before its ``peer_joined``), and
  any other message about a user (its events, ``peer_stalled``) first flushes
  that user's pending notice, so nothing about a peer arrives before its
  ``peer_joined`` (``RelayCore.to_member``);
- a batch holds at most :data:`PER_TICK` notices, departures first; the rest
  carry over, in order, to the next tick (and keep coalescing meanwhile).

A joining member still gets its ``peer_joined`` list of who is there at once
(after ``joined``); only notices of changes wait for the tick.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol, TypeVar

from posecast.protocol import PeerJoined, PeerLeft

if TYPE_CHECKING:
    from posecast.protocol.events import Message

__all__ = ["PER_TICK", "Presence", "flusher"]

#: Notices one member gets per room tick at most (the event queue holds 256).
PER_TICK = 64


@dataclass(slots=True)
class _Change:
    """What one member must still hear about one user."""

    #: The member knew the user as present when this change began.
    known: bool
    #: The departure of the user it knew (sent if ``known``), the first one.
    left: PeerLeft | None
    #: The user's announcement as it is now (None: the user is gone).
    joined: PeerJoined | None


class Presence:
    """One member's presence notices not sent yet, net per user, in arrival order."""

    __slots__ = ("_changes",)

    def __init__(self) -> None:
        self._changes: dict[int, _Change] = {}

    def __len__(self) -> int:
        return len(self._changes)

    def joined(self, notice: PeerJoined) -> None:
        """``notice.user`` joined (it was not in the room)."""
        change = self._changes.get(notice.user)
        if change is None:
            self._changes[notice.user] = _Change(False, None, notice)
        else:
            change.joined = notice

    def left(self, notice: PeerLeft) -> None:
        """``notice.user`` left (it was in the room)."""
        change = self._changes.get(notice.user)
        if change is None:
            self._changes[notice.user] = _Change(True, notice, None)
        elif not change.known:  # announced to nobody yet: nothing to tell
            del self._changes[notice.user]
        else:
            change.joined = None

    def clear(self) -> None:
        """Forget every pending notice (the member gets the room anew, or leaves)."""
        self._changes.clear()

    def take_user(self, user: int | None) -> list[PeerJoined | PeerLeft]:
        """The pending notices about ``user`` alone, now (before other news of it)."""
        change = self._changes.pop(user, None) if user is not None else None
        if change is None:
            return []
        out: list[PeerJoined | PeerLeft] = []
        if change.known and change.left is not None:
            out.append(change.left)
        if change.joined is not None:
            out.append(change.joined)
        return out

    def take(self, limit: int = PER_TICK) -> list[PeerJoined | PeerLeft]:
        """At most ``limit`` notices: departures first, then arrivals, each in the
        order of their users' first change; the rest stays for the next call."""
        out: list[PeerJoined | PeerLeft] = []
        changes = self._changes
        for change in changes.values():
            if len(out) >= limit:
                break
            if change.known and change.left is not None:
                out.append(change.left)
                change.known, change.left = False, None
        for user, change in list(changes.items()):
            if change.known:  # its departure did not fit: its arrival waits too
                continue
            if change.joined is not None:
                if len(out) >= limit:
                    continue
                out.append(change.joined)
            del changes[user]
        return out


# What the hook needs of a room and its members (``server.room``; no import of it:
# the room holds a Presence, so the import points from the room to here).
class _Member(Protocol):
    @property
    def user(self) -> int: ...
    @property
    def parked(self) -> bool: ...
    @property
    def presence(self) -> Presence: ...


class _Room(Protocol):
    @property
    def members(self) -> Mapping[int, _Member]: ...


P = TypeVar("P")


def flusher(
    connected: Callable[[int], P | None], send: Callable[[P, Message], None]
) -> Callable[[_Room], None]:
    """The room-tick hook: each member of the room gets its pending notices through
    ``send`` to its live connection (``connected``); a parked member's are dropped
    (it gets the room anew when it resumes)."""

    def flush(room: _Room) -> None:
        for member in list(room.members.values()):
            presence = member.presence
            if not len(presence):
                continue
            peer = connected(member.user)
            if member.parked or peer is None:
                presence.clear()
                continue
            for notice in presence.take():
                send(peer, notice)

    return flush
