"""Access tokens on a live connection: checked at join, renewed, expired.

The token format and its HMAC are ``server/auth.py``'s; this module applies
them to a connection of the relay core (``server/core.py``): a join of a server
with a secret needs a token for that room (refused: ``unauthorized``, close
1008), one connection per token user and room (``user-taken``), and the
connection is closed when its token expires unless a ``renew`` moves the
deadline. A resumed connection's join must carry a token of the parked member's
user (else ``unauthorized``, and the member stays parked: ``server.resume``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from posecast.protocol import ErrorCode, Join, Renew
from posecast.protocol.events import Event
from posecast.server import resume
from posecast.server.auth import TokenClaims, TokenError, token_permits, verify_token
from posecast.server.limits import error_message, normalise_room

if TYPE_CHECKING:
    from posecast.server.peer import Peer
    from posecast.server.ports import Relay

__all__ = [
    "EVENT_TYPE",
    "admit_event",
    "admit_join",
    "event_dropped",
    "expired",
    "joinable_room",
    "renew",
]

#: What follows the map header of an event frame as ``protocol.messages`` writes it
#: ("type" first): the key "type" and the value "event", msgpack fixstrs. The core
#: compares a frame's bytes 1-11 with it before it calls :func:`event_dropped`.
EVENT_TYPE = b"\xa4type\xa5event"


def joinable_room(event: Event, secret: str | None, wall: float) -> str | None:
    """The room a join event names, if the join may go on (None: not a join, a name
    the core refuses, or a token that does not admit to it: then the core refuses
    it, and nothing is opened or claimed for a client that may not join)."""
    if not isinstance(event, Join):
        return None
    try:
        name = normalise_room(event.room)
    except ValueError:
        return None
    return name if token_permits(secret, event.token, name, wall) else None


def _unauthorized(core: Relay, peer: Peer, exc: TokenError, what: str) -> None:
    core.send(peer, error_message(ErrorCode.UNAUTHORIZED, str(exc), what))
    core.close_peer(peer, 1008, str(exc))


def admit_join(core: Relay, peer: Peer, join: Join, name: str, now: float, wall: float) -> bool:
    """Whether ``join`` of room ``name`` may go on (an open server: always); on a server
    with a secret, the token's user becomes the peer's name and its expiry a deadline."""
    secret = core.config.secret
    if secret is None:
        return _join_rate(core, peer, None, now)
    try:
        claims: TokenClaims = verify_token(secret, join.token, name, wall)
    except TokenError as exc:
        _unauthorized(core, peer, exc, "join")
        return False
    if not _join_rate(core, peer, claims.user, now):
        return False
    if peer.parked is not None and peer.parked.name != claims.user:
        resume.refuse(core, peer, "join", now)  # (the parked member stays parked)
        return False
    back = peer.parked is not None
    room = core.rooms.get(name)
    if not back and room is not None and room.has_member_named(claims.user):
        core.refuse(
            peer,
            ErrorCode.USER_TAKEN,
            f"user {claims.user!r} is already in room {name!r} on another connection",
            "join",
            now,
        )
        return False
    peer.name = claims.user
    core.token_expires_at(peer, now + (claims.exp - wall))
    return True


def renew(core: Relay, peer: Peer, event: Renew, now: float, wall: float) -> None:
    """A fresh token for the same room and user moves the connection's deadline."""
    secret = core.config.secret
    if secret is None or peer.room is None:
        return  # nothing expires on an open server
    try:
        claims = verify_token(secret, event.token, peer.room.name, wall)
        if claims.user != peer.name:
            raise TokenError(f"access token is for user {claims.user!r}, not {peer.name!r}")
    except TokenError as exc:
        _unauthorized(core, peer, exc, "renew")
        return
    core.token_expires_at(peer, now + (claims.exp - wall))


def expired(core: Relay, peer: Peer) -> None:
    """``peer``'s access token expired without a renew: ``unauthorized``, close 1008."""
    core.token_expiries += 1
    core.send(peer, error_message(ErrorCode.UNAUTHORIZED, "access token expired; renew it"))
    core.close_peer(peer, 1008, "access token expired")


def _join_rate(core: Relay, peer: Peer, user: str | None, now: float) -> bool:
    """Whether a join is within its address's (and token user's) join rate, across
    connections (``server/guard.py``); over it: ``room-full``, try later."""
    if core.handshakes.guard.join(peer.address, user, now):
        return True
    rate = core.handshakes.guard.joins.rate
    why = f"too many joins from this address or user (over {rate:g}/s); try later"
    core.refuse(peer, ErrorCode.ROOM_FULL, why, "join", now)
    return False


def event_dropped(core: Relay, peer: Peer, data: bytes | str, now: float) -> bool:
    """Drop an event frame of a member whose connection's bucket is empty before
    decoding it (a peek at its first 12 bytes; counted as :func:`admit_event` counts
    it after a decode): a flood costs the relay little per dropped event. A frame
    the peek does not recognise, or that fits the bucket, is decoded as any other."""
    if (
        peer.room is None
        or peer.close_request is not None
        or type(data) is not bytes
        or data[1:12] != EVENT_TYPE
        or data[0] & 0xF0 != 0x80  # a fixmap (an event has at most 6 fields)
        or core.is_spectator(peer.user)  # its events are refused, not dropped
        or peer.would_admit(core.config.max_update_rate, now)
    ):
        return False
    peer.frames_in += 1
    peer.bytes_in += len(data)
    core.admit_update(peer, now)  # drops and counts it; a long flood is closed 1008
    return True


def admit_event(core: Relay, peer: Peer, now: float) -> bool:
    """Whether an event of ``peer`` is within its address's and token user's rate, across
    connections (``server/guard.py``), and within its connection's update bucket
    (``RelayCore.admit_update``); over the former, dropped (counted), closed 1008."""
    if not core.admit_update(peer, now):
        return False
    user = peer.name if core.config.secret is not None else None
    guard = core.handshakes.guard
    if guard.event(peer.address, user, now):
        return True
    peer.flood_drops += 1
    rate = guard.events.rate
    core.close_peer(peer, 1008, f"event flood: over {rate:g} events/s from this address or user")
    return False
