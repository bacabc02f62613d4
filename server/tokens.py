"""Access tokens on a live connection: checked at join, renewed, expired; join and event rates.

The token format and its HMAC are ``server/auth.py``'s; this part of the relay
core (``server/core.py``), :class:`Tokens`, applies them to its connections: a
join of a server with a secret needs a token for that room (refused:
``unauthorized``, close 1008), one connection per token user and room
(``user-taken``), and the connection is closed when its token expires unless a
``renew`` moves the deadline. A resumed connection's join must carry a token of the
parked member's user (else ``unauthorized``, and the member stays parked:
``server.resume``). Joins and events are also held to their address's and token
user's rates across connections (``server/guard.py``).

Its own state: the connections' token deadlines and the count of expiries. The
pre-join check (:func:`joinable_room`) is a plain function: the core asks it
before a join is held for a recording or a cluster claim (``server.joins``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING

from posecast.protocol import ErrorCode, Join, Renew
from posecast.protocol.events import Event
from posecast.server import resume
from posecast.server.auth import TokenClaims, TokenError, token_permits, verify_token
from posecast.server.limits import Deadlines, error_message, normalise_room

if TYPE_CHECKING:
    from posecast.server.peer import Peer
    from posecast.server.ports import Relay

__all__ = ["EVENT_TYPE", "Tokens", "joinable_room"]

#: What follows the map header of an event frame as ``protocol.messages`` writes it
#: ("type" first): the key "type" and the value "event", msgpack fixstrs. The core
#: compares a frame's bytes 1-11 with it before it calls :meth:`Tokens.event_dropped`.
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


class Tokens:
    """Access tokens of the relay's connections, and their join and event rates."""

    def __init__(self, relay: Relay, peers: Mapping[int, Peer]) -> None:
        self.relay = relay
        self.peers = peers
        self._deadlines = Deadlines(self._due)
        #: Connections closed because their access token expired (a metric).
        self.expiries = 0

    # -- a token's life ------------------------------------------------------------------

    def admit_join(self, peer: Peer, join: Join, name: str, now: float, wall: float) -> bool:
        """Whether ``join`` of room ``name`` may go on (an open server: always); on a
        server with a secret, the token's user becomes the peer's name and its expiry a
        deadline."""
        core = self.relay
        secret = core.config.secret
        if secret is None:
            return self._join_rate(peer, None, now)
        try:
            claims: TokenClaims = verify_token(secret, join.token, name, wall)
        except TokenError as exc:
            self._unauthorized(peer, exc, "join")
            return False
        if not self._join_rate(peer, claims.user, now):
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
        self._expires_at(peer, now + (claims.exp - wall))
        return True

    def renew(self, peer: Peer, event: Renew, now: float, wall: float) -> None:
        """A fresh token for the same room and user moves the connection's deadline."""
        secret = self.relay.config.secret
        if secret is None or peer.room is None:
            return  # nothing expires on an open server
        try:
            claims = verify_token(secret, event.token, peer.room.name, wall)
            if claims.user != peer.name:
                raise TokenError(f"access token is for user {claims.user!r}, not {peer.name!r}")
        except TokenError as exc:
            self._unauthorized(peer, exc, "renew")
            return
        self._expires_at(peer, now + (claims.exp - wall))

    def next_deadline(self) -> float | None:
        """When the next connection's access token expires (None: none)."""
        return self._deadlines.next()

    def expire(self, now: float) -> None:
        """Close every connection whose access token expired without a renew:
        ``unauthorized``, close 1008."""
        core = self.relay
        for conn in self._deadlines.pop_due(now):
            peer = self.peers[conn]
            self.expiries += 1
            core.send(peer, error_message(ErrorCode.UNAUTHORIZED, "access token expired; renew it"))
            core.close_peer(peer, 1008, "access token expired")

    def _expires_at(self, peer: Peer, deadline: float) -> None:
        """Close ``peer`` at ``deadline`` (server clock) unless it renews its token."""
        peer.token_deadline = deadline
        self._deadlines.add(peer.conn, deadline)
        self.relay.emit_rearm()

    def _due(self, conn: int, deadline: float) -> bool:
        peer = self.peers.get(conn)
        return peer is not None and peer.token_deadline == deadline and not peer.close_request

    def _unauthorized(self, peer: Peer, exc: TokenError, what: str) -> None:
        self.relay.send(peer, error_message(ErrorCode.UNAUTHORIZED, str(exc), what))
        self.relay.close_peer(peer, 1008, str(exc))

    # -- join and event rates across connections ----------------------------------------------

    def _join_rate(self, peer: Peer, user: str | None, now: float) -> bool:
        """Whether a join is within its address's (and token user's) join rate, across
        connections (``server/guard.py``); over it: ``room-full``, try later."""
        core = self.relay
        if core.handshakes.guard.join(peer.address, user, now):
            return True
        rate = core.handshakes.guard.joins.rate
        why = f"too many joins from this address or user (over {rate:g}/s); try later"
        core.refuse(peer, ErrorCode.ROOM_FULL, why, "join", now)
        return False

    def event_dropped(self, peer: Peer, data: bytes | str, now: float) -> bool:
        """Drop an event frame of a member whose connection's bucket is empty before
        decoding it (a peek at its first 12 bytes; counted as :meth:`admit_event`
        counts it after a decode): a flood costs the relay little per dropped event. A
        frame the peek does not recognise, or that fits the bucket, is decoded as any
        other."""
        core = self.relay
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

    def admit_event(self, peer: Peer, now: float) -> bool:
        """Whether an event of ``peer`` is within its address's and token user's rate,
        across connections (``server/guard.py``), and within its connection's update
        bucket (``RelayCore.admit_update``); over the former, dropped (counted), closed
        1008."""
        core = self.relay
        if not core.admit_update(peer, now):
            return False
        user = peer.name if core.config.secret is not None else None
        guard = core.handshakes.guard
        if guard.event(peer.address, user, now):
            return True
        peer.flood_drops += 1
        rate = guard.events.rate
        core.close_peer(
            peer, 1008, f"event flood: over {rate:g} events/s from this address or user"
        )
        return False
