"""Resume after a dropped connection: parked members, their tokens and deadlines.

A client that says ``hello.resumable`` gets a resume token in ``welcome``. When
its connection ends without a ``bye`` (the socket dropped, keepalive gave up),
its member is *parked* instead of leaving: it stays in its room with its user
id, streams and last poses, peers get ``peer_stalled``, and events for it wait
in its queue (bounded as always). Within ``window`` seconds a new connection
that says ``hello.resume=TOKEN`` gets the same user id back, and its next join
of the same room and streams re-binds the parked member: the same stream ids,
the queued events first, a key snapshot, ``peer_resumed`` to the peers and a
``disconnected`` drops record (the gap) in the recording. A token is good for
one resume; the resumed connection gets a new one. When the window closes
first, the member leaves as any other (``peer_left``, reason "gone").

A resume token is a credential bound to the session it was given to: its first
``ID_LENGTH`` characters name the parked member, the rest is a secret compared in
constant time (``hmac.compare_digest``). A hello naming a parked member without
its secret is refused (``unauthorized``, close 1008); on a relay with a secret the
resumed connection's join must also carry an access token of the same user (else
``unauthorized``, close 1008). Neither refusal disturbs the parked member: it
stays parked under its token (:func:`unclaim`), so its own client still resumes.

A member whose connection stays up but whose pose updates stop for
``stall_after`` seconds (a frozen browser tab: its network process still answers
websocket pings, so keepalive never fires) is announced the same way: peers get
``peer_stalled`` (the same message, no new field: its streams stay frozen at their
last pose, as a parked member's), and ``peer_resumed`` at its next accepted
update (:class:`Silence`). A member that has never published is never silent. A
silent member whose connection then drops is parked without a second
``peer_stalled``; a resumed one is watched again from its resume.

Sans-I/O like the core: the time is an argument.
"""

from __future__ import annotations

import heapq
import hmac
import secrets
from dataclasses import replace
from typing import TYPE_CHECKING

from posecast.protocol import (
    ErrorCode,
    Hello,
    Join,
    Joined,
    PeerLeft,
    PeerResumed,
    PeerStalled,
    UserEvent,
    decode_message,
)
from posecast.server import objects, rates
from posecast.server.limits import Deadlines, error_message
from posecast.server.parked import Parked
from posecast.server.room import Member, Room

if TYPE_CHECKING:
    from posecast.protocol.events import Message
    from posecast.server.core import RelayCore
    from posecast.server.peer import Peer

__all__ = [
    "ID_LENGTH",
    "Parked",
    "Parking",
    "Silence",
    "gone",
    "hello",
    "park",
    "parkable",
    "restore",
    "resume_join",
    "unclaim",
]

#: Characters of a resume token that name its parked member (the rest is its secret).
ID_LENGTH = 12


class Parking:
    """Resume tokens of live connections and the members parked under them."""

    def __init__(self, window: float) -> None:
        self.window = window
        #: token id -> parked member (a token names one user; it is spent by a resume).
        self._parked: dict[str, Parked] = {}
        self._deadlines = Deadlines(self._still_parked)
        self._by_conn: dict[int, str] = {}
        #: Resumes done, windows closed, and resumes refused (a wrong secret, another
        #: user's access token: ``posecast_resumes_refused_total``).
        self.resumes = self.expired = self.refused = 0

    @staticmethod
    def new_token() -> str:
        """A token id and its secret (36 URL-safe characters: 72 + 144 random bits)."""
        return secrets.token_urlsafe(ID_LENGTH * 3 // 4) + secrets.token_urlsafe(18)

    def _still_parked(self, conn: int, deadline: float) -> bool:
        key = self._by_conn.get(conn)
        parked = None if key is None else self._parked.get(key)
        return parked is not None and parked.deadline == deadline

    def park(self, conn: int, parked: Parked) -> None:
        key = parked.token[:ID_LENGTH]
        self._parked[key] = parked
        self._by_conn[conn] = key
        self._deadlines.add(conn, parked.deadline)

    def find(self, token: str, now: float) -> Parked | None:
        """The member parked under ``token``'s id, window open (its secret unchecked)."""
        parked = self._parked.get(token[:ID_LENGTH])
        return None if parked is None or parked.deadline <= now else parked

    @staticmethod
    def matches(parked: Parked, token: str) -> bool:
        """Whether ``token`` is ``parked``'s whole token (constant time in its secret)."""
        return hmac.compare_digest(parked.token.encode(), token.encode())

    def claim(self, token: str | None, now: float) -> Parked | None:
        """The member parked under ``token`` if its window is still open (spent)."""
        parked = None if token is None else self.find(token, now)
        if parked is None or token is None or not self.matches(parked, token):
            return None
        del self._parked[parked.token[:ID_LENGTH]]
        self._by_conn.pop(parked.conn, None)
        self.resumes += 1
        return parked

    def has(self, token: str) -> bool:
        """Whether a member is parked under ``token``'s id (its secret unchecked)."""
        return token[:ID_LENGTH] in self._parked

    def tokens(self) -> dict[int, str]:
        """Parked users and the tokens they resume with."""
        return {p.user: p.token for p in self._parked.values()}

    def holds(self, user: int) -> bool:
        """Whether ``user`` is parked (its id must not be given to anyone else)."""
        return any(p.user == user for p in self._parked.values())

    def next(self) -> float | None:
        return self._deadlines.next()

    def expire(self, now: float) -> list[Parked]:
        """The parked members whose window closed by ``now``, removed."""
        out = []
        for conn in self._deadlines.pop_due(now):
            key = self._by_conn.pop(conn)
            parked = self._parked.pop(key, None)
            if parked is not None:
                self.expired += 1
                out.append(parked)
        return out


# -- the core's side (functions of RelayCore, kept here so that core.py stays small) ------


def hello(core: RelayCore, peer: Peer, event: Hello, now: float) -> None:
    """Welcome ``peer``: a resumed user's id back, or a new one; a token if resumable.
    A token naming a parked member without its secret is refused (1008)."""
    parking = core.parking
    if event.resume:
        found = parking.find(event.resume, now)
        if found is not None and not parking.matches(found, event.resume):
            refuse(core, peer, "hello", now)
            return
    parked = parking.claim(event.resume, now) if event.resume else None
    if parked is not None:
        peer.user, peer.name, peer.parked = parked.user, parked.name, parked
    else:
        # A member forwarded by another cluster node comes with the id it was given there.
        peer.user = core.users.take() if peer.preset_user is None else peer.preset_user
        peer.name = event.agent or f"user{peer.user}"
    core.bind_user(peer.user, peer)
    welcome = peer.session.make_welcome(peer.user, now)
    if parking.window > 0 and (event.resumable or parked is not None):
        peer.resume_token = parking.new_token()
        welcome = replace(welcome, resume=peer.resume_token, resumed=parked is not None)
    core.send(peer, welcome)


def refuse(core: RelayCore, peer: Peer, what: str, now: float) -> None:
    """Refuse a resume (``unauthorized``, close 1008); the parked member is not touched."""
    core.parking.refused += 1
    reason = "resume refused: not this session's resume token or user"
    core.send(peer, error_message(ErrorCode.UNAUTHORIZED, reason, what))
    core.close_peer(peer, 1008, reason)


def unclaim(core: RelayCore, parked: Parked, now: float) -> None:
    """A resumed connection that ended before its join re-bound ``parked`` (refused, or
    gone): the member is parked again under its token until its window closes."""
    room = parked.room
    if parked.deadline <= now or room.retired or room.members.get(parked.user) is not parked.member:
        gone(core, parked, now)
        return
    core.parking.resumes -= 1
    core.parking.park(parked.conn, parked)
    core.emit_rearm()


def parkable(core: RelayCore, peer: Peer) -> bool:
    """Whether a connection that just ended is parked rather than leaving: it asked
    to be resumable, is a (non-spectator) member, and neither side said goodbye."""
    return (
        peer.resume_token is not None
        and peer.member is not None
        and peer.room is not None
        and not peer.room.retired
        and peer.close_request is None
        and not core.is_spectator(peer.user)
    )


def park(core: RelayCore, peer: Peer, now: float) -> None:
    """Keep ``peer``'s member in its room for the resume window; peers hear it stalled."""
    room, member = peer.room, peer.member
    assert room is not None and member is not None and peer.user is not None
    assert peer.resume_token is not None
    member.parked = True
    parking = core.parking
    parking.park(
        peer.conn,
        Parked(peer.user, peer.name, room, member, now, now + parking.window,
               peer.resume_token, peer.conn),
    )  # fmt: skip
    if not member.silent:  # (a silent member's peers have heard it stalled)
        _tell_peers(core, room, member, PeerStalled(user=peer.user))
    peer.room = peer.member = None
    core.emit_rearm()


def gone(core: RelayCore, parked: Parked, now: float) -> None:
    """A parked member whose window closed: it leaves (``peer_left``, reason "gone")."""
    room, user = parked.room, parked.user
    if room.members.get(user) is parked.member:
        objects.owner_left(core, room, user, now)
        room.remove(user)
        core.rescheduled(room)
        room.record(
            "drop",
            {"kind": "disconnected", "user": user, "first_time": parked.since,
             "last_time": now, "count": 1},
            now,
        )  # fmt: skip
        room.record("presence", {"kind": "leave", "user": user, "reason": "gone"}, now)
        for other in list(room.members.values()):
            if not core.is_spectator(other.user):
                core.to_member(other, PeerLeft(user=user, reason="gone"))
        core.forget_room_if_empty(room, now)
    if core.connected(user) is None:
        core.users.give_back(user)


def resume_join(core: RelayCore, peer: Peer, join: Join, name: str, now: float) -> bool:
    """Re-bind a resumed peer's parked member if ``join`` asks for its room and streams;
    True if it did. Otherwise the parked member leaves and the join goes on as new."""
    parked, peer.parked = peer.parked, None
    if parked is None:
        return False
    room, member = parked.room, parked.member
    if room.retired or room.name != name or set(join.streams) != set(member.streams):
        gone(core, parked, now)
        return False
    old = member.outbox
    member.outbox, member.parked = peer.outbox, False
    member.compact, member.echo = join.codec == "compact", join.echo
    member.velocities, member.sends_velocities = join.wants_velocities, join.sends_velocities
    member.rate = rate = rates.granted(core.config.max_rate, join)
    rates.attach(core.config, peer, member, join)  # its link emulation, its auto rate
    member.last_version = member.delivered_version = 0
    room.set_rate(member.user, rate, now)  # a key snapshot on its next tick
    peer.room, peer.member = room, member
    shared = objects.joined_objects(room)
    core.send(peer, Joined(room=join.room, streams=member.streams, rate=rate, objects=shared))
    for other in list(room.members.values()):
        if other.user == member.user or core.is_spectator(other.user):
            continue
        core.send(peer, Room.announce(other))
        core.to_member(other, PeerResumed(user=member.user))
    objects.restore(core, peer, room)
    member.silent = False  # peers heard it resume
    core.silence.watch(room, member, now)
    # The events it missed, in order, once it knows the room; presence notices and
    # pongs still queued from before the drop are stale (it just got the room anew).
    for data in old.events:
        if decode_message(data).TYPE == UserEvent.TYPE and not peer.outbox.offer_event(data):
            break
    old.events.clear()
    room.record(
        "drop",
        {"kind": "disconnected", "user": member.user, "first_time": parked.since,
         "last_time": now, "count": 1},
        now,
    )  # fmt: skip
    core.rescheduled(room)
    return True


def restore(
    core: RelayCore,
    room: Room,
    member: Member,
    token: str,
    now: float,
) -> bool:
    """Park ``member`` of a room whose cluster node was lost (``server.node``), so that
    its client resumes here with ``token`` as on the node it was on: the same user
    id and stream ids. False if the user or one of its stream ids is taken here."""
    user = member.user
    if user in room.members or core.connected(user) is not None or core.parking.holds(user):
        return False
    if any(not room.stream_ids.reserve(sid) for sid in member.streams.values()):
        return False
    core.users.reserve(user)
    room.add(member, now)
    member.parked = True
    conn = core.new_conn()  # a connection id no socket will have: the parking's key
    parking = core.parking
    parking.park(conn, Parked(user, member.name, room, member, now, now + parking.window,
                              token, conn))  # fmt: skip
    room.record(
        "presence",
        {"kind": "join", "user": user, "name": member.name, "label": member.label,
         "streams": member.streams, "rate": member.rate},
        now,
    )  # fmt: skip
    core.rescheduled(room)
    core.emit_rearm()
    return True


def _tell_peers(core: RelayCore, room: Room, member: Member, notice: Message) -> None:
    """Queue ``notice`` (about ``member``) to every other member but spectators."""
    for other in list(room.members.values()):
        if other.user != member.user and not core.is_spectator(other.user):
            core.to_member(other, notice)


class Silence:
    """Publishers whose updates stopped while their connection stays up.

    Each publishing member has one deadline at most, at its last update plus
    ``after``: met with no newer update, its peers hear ``peer_stalled``;
    its next update brings ``peer_resumed``. An accepted update costs a store and
    two flag checks (a deadline is added only when a member starts publishing
    again), so the heap holds one entry per publisher, moved when it is met.
    """

    def __init__(self, after: float) -> None:
        #: The bound (s); 0: off.
        self.after = after
        self._heap: list[tuple[float, int, Room, Member]] = []
        self._seq = 0
        #: Members announced stalled for silence, and announced back.
        self.stalls = self.resumes = 0

    def updated(self, core: RelayCore, room: Room, member: Member, now: float) -> None:
        """``member`` of ``room`` had an update accepted at ``now``."""
        member.last_update = now
        if member.silent:
            member.silent = False
            self.resumes += 1
            _tell_peers(core, room, member, PeerResumed(user=member.user))
        if not member.watched and self.after > 0:
            self._push(now + self.after, room, member)
            core.emit_rearm()

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

    def expire(self, core: RelayCore, now: float) -> None:
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
                _tell_peers(core, room, member, PeerStalled(user=member.user))
            else:
                self._push(last + self.after, room, member)
