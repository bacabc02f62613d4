"""Resume after a dropped connection: parking a member, resuming it, its window closing.

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

The resume tokens and the parked members are ``server.parking``'s table; a member
whose connection stays up but whose updates stop is ``server.silence``'s. The
rules here act on the core through its port (``server.ports.Relay``).

Sans-I/O like the core: the time is an argument.
"""

from __future__ import annotations

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
from posecast.server.limits import error_message
from posecast.server.member import Member
from posecast.server.parked import Parked
from posecast.server.room import Room

if TYPE_CHECKING:
    from posecast.server.peer import Peer
    from posecast.server.ports import Relay

__all__ = [
    "gone",
    "hello",
    "park",
    "parkable",
    "restore",
    "resume_join",
    "unclaim",
]


def hello(core: Relay, peer: Peer, event: Hello, now: float) -> None:
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


def refuse(core: Relay, peer: Peer, what: str, now: float) -> None:
    """Refuse a resume (``unauthorized``, close 1008); the parked member is not touched."""
    core.parking.refused += 1
    reason = "resume refused: not this session's resume token or user"
    core.send(peer, error_message(ErrorCode.UNAUTHORIZED, reason, what))
    core.close_peer(peer, 1008, reason)


def unclaim(core: Relay, parked: Parked, now: float) -> None:
    """A resumed connection that ended before its join re-bound ``parked`` (refused, or
    gone): the member is parked again under its token until its window closes."""
    room = parked.room
    if parked.deadline <= now or room.retired or room.members.get(parked.user) is not parked.member:
        gone(core, parked, now)
        return
    core.parking.resumes -= 1
    core.parking.park(parked.conn, parked)
    core.emit_rearm()


def parkable(core: Relay, peer: Peer) -> bool:
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


def park(core: Relay, peer: Peer, now: float) -> None:
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
        core.tell_peers(room, member, PeerStalled(user=peer.user))
    peer.room = peer.member = None
    core.emit_rearm()


def gone(core: Relay, parked: Parked, now: float) -> None:
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
                other.presence.left(PeerLeft(user=user, reason="gone"))
        core.forget_room_if_empty(room, now)
    if core.connected(user) is None:
        core.users.give_back(user)


def resume_join(core: Relay, peer: Peer, join: Join, name: str, now: float) -> bool:
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
    member.presence.clear()  # it gets the room anew below
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
    core: Relay,
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
