"""Admission and membership: who may connect, which join waits, joins a room, leaves it.

One part of the relay core (``server/core.py``), with its own state: the deadlines
of connections not joined yet and the spectators. Its rules:

==================  ==========================================================
a connection ...    this part ...
==================  ==========================================================
opens               admits it under ``max_connections`` (and per source
                    address, ``limits.Admission``); refused: the core closes
                    it 1013. Admitted: it must join within ``join_timeout``
                    (:meth:`Joins.unjoined` names those that did not)
sends a join        holds it (:meth:`Joins.hold`) while this node must claim
                    its room in a cluster, or a recording of a new room opens;
                    holds a hello resuming a member this node does not park.
                    The pre-join check (name and token) is
                    ``tokens.joinable_room``, the one place it is written
joins a room        normalises the name (``bad-room``), checks its token
                    (``server.tokens``), re-binds a parked member
                    (``server.resume``), refuses over ``max_rooms`` /
                    ``max_members`` / ``max_recorded_rooms`` (``room-full``),
                    creates the room, answers ``joined``, tells it the members
                    and them of it (spectators: nobody hears of one), records it
leaves              its objects are released, the room hears ``peer_left`` at
                    its next tick, an empty room goes (its recording finished)
==================  ==========================================================

It acts on the core through its port (``server.ports.Relay``) and on the room
table and the capacity through their public methods. Sans I/O: time is an argument.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING

from posecast.protocol import ErrorCode, Hello, Join, Joined, PeerLeft
from posecast.protocol.events import Event
from posecast.server import objects, rates, resume
from posecast.server.actions import Hold
from posecast.server.limits import Admission, Deadlines, normalise_room
from posecast.server.member import Member
from posecast.server.room import Room
from posecast.server.tokens import Tokens, joinable_room

if TYPE_CHECKING:
    from posecast.server.capacity import Capacity
    from posecast.server.peer import Peer
    from posecast.server.ports import ClusterView, Relay
    from posecast.server.rooms import RoomTable

__all__ = ["Joins"]


class Joins:
    """Admission of connections, the join deadline, joins and leaves, spectators."""

    def __init__(
        self,
        relay: Relay,
        peers: Mapping[int, Peer],
        table: RoomTable,
        capacity: Capacity,
        admission: Admission,
        tokens: Tokens,
    ) -> None:
        self.relay = relay
        self.config = relay.config
        self.peers = peers
        self.table = table
        self.capacity = capacity
        self.admission = admission
        self.tokens = tokens
        self._deadlines = Deadlines(self._unjoined)
        #: Connections whose join (or resuming hello) the adapter holds (:meth:`hold`):
        #: the join was sent, so its deadline waits until :meth:`unhold`.
        self._holding: set[int] = set()
        #: Users who joined as spectators: they publish nothing and nobody hears of them.
        #: (The core reads this set on every update: a spectator's is refused.)
        self.spectators: set[int] = set()

    # -- admission ---------------------------------------------------------------------

    def admit(self, peer: Peer, now: float) -> str | None:
        """Admit a connection that just opened; why not (None: admitted, and due to
        join within ``join_timeout``)."""
        refused = self.admission.admit(peer.address)
        if refused is None:
            peer.admitted = True
            self._deadlines.add(peer.conn, now + self.config.join_timeout)
        return refused

    def release(self, peer: Peer) -> None:
        """``peer``'s connection ended: its admission place is free."""
        self._holding.discard(peer.conn)
        if peer.admitted:
            self.admission.release(peer.address)

    def next_deadline(self) -> float | None:
        """When the next connection not joined yet is due to be closed (None: none)."""
        return self._deadlines.next()

    def unjoined(self, now: float) -> list[int]:
        """The connections that have not joined ``join_timeout`` after they opened. One
        whose join came in time but is held (a recording opening, a cluster claim) is
        looked at again a ``join_timeout`` later instead."""
        due = self._deadlines.pop_due(now)
        for conn in self._holding.intersection(due):
            self._deadlines.add(conn, now + max(self.config.join_timeout, 1.0))
        return [conn for conn in due if conn not in self._holding]

    def _unjoined(self, conn: int, deadline: float) -> bool:
        peer = self.peers.get(conn)
        return (
            peer is not None and peer.room is None and peer.close_request is None
        ) and not peer.forwarded

    # -- what waits before a join ---------------------------------------------------------

    def room_to_open(self, event: Event, wall: float) -> str | None:
        """The room a recording server must open (off the loop) before ``event``."""
        if self.config.record_dir is None:
            return None
        name = joinable_room(event, self.config.secret, wall)
        if name is None or name in self.table.rooms or self.table.refusal(name) is not None:
            return None
        return name

    def hold(
        self, conn: int, event: Event, wall: float, cluster: ClusterView | None
    ) -> Hold | None:
        """Whether ``event`` of ``conn`` must wait before the core handles it (None: no).

        In a cluster, a join of a room this node must claim first waits for the
        claim, and a hello resuming a member not parked here waits for the cluster's
        lookup; on a recording server, a join that creates a room waits for its
        recording to open. While held, ``conn``'s join deadline waits (its join came
        in time) until :meth:`unhold`.
        """
        held = self._hold(conn, event, wall, cluster)
        if held is not None and conn in self.peers:
            self._holding.add(conn)
        return held

    def _hold(
        self, conn: int, event: Event, wall: float, cluster: ClusterView | None
    ) -> Hold | None:
        if cluster is not None:
            name = joinable_room(event, self.config.secret, wall)
            if name is not None and cluster.must_claim(name):
                return Hold(conn, "claim", name)
            parking = self.relay.parking
            if isinstance(event, Hello) and event.resume and not parking.has(event.resume):
                return Hold(conn, "resume", token=event.resume)
        room = self.room_to_open(event, wall)
        return None if room is None else Hold(conn, "open", room)

    def unhold(self, conn: int) -> None:
        """The hold of ``conn`` is over: the held event comes next, the deadline holds again."""
        self._holding.discard(conn)

    # -- joining and leaving ----------------------------------------------------------------

    def is_spectator(self, user: int | None) -> bool:
        """Whether ``user`` joined as a spectator (publishes nothing, unannounced)."""
        return user in self.spectators

    def join(self, peer: Peer, join: Join, now: float, wall: float) -> None:
        """``peer`` asks to join ``join.room`` (``joined`` echoes the name as asked)."""
        relay = self.relay
        try:
            name = normalise_room(join.room)
        except ValueError as exc:
            relay.refuse(peer, ErrorCode.BAD_ROOM, str(exc), "join", now)
            return
        if not self.tokens.admit_join(peer, join, name, now, wall):
            return
        assert peer.user is not None  # the state table puts hello before join
        if resume.resume_join(relay, peer, join, name, now):
            return
        if (refused := self.table.refusal(name)) is not None:
            self.capacity.count(ErrorCode.ROOM_FULL)
            relay.refuse(peer, ErrorCode.ROOM_FULL, refused, "join", now, charge=False)
            return
        room = self.table.room_for(name)
        streams = room.allocate_streams(join.streams)
        shared, rate = objects.joined_objects(room), rates.granted(self.config.max_rate, join)
        relay.send(peer, Joined(room=join.room, streams=streams, rate=rate, objects=shared))
        member = Member(
            peer.user,
            peer.name,
            streams,
            rate,
            peer.outbox,
            label=join.label,
            velocities=join.wants_velocities,
            sends_velocities=join.sends_velocities,
            compact=join.codec == "compact",
            echo=join.echo,
        )
        rates.attach(self.config, peer, member, join)  # its link emulation, its auto rate
        if join.spectator:
            self.spectators.add(peer.user)
        self._introduce(peer, member, room)
        objects.introduce(relay, peer, room)
        room.add(member, now)
        relay.rescheduled(room)
        peer.room, peer.member = room, member
        if room.recorded and not join.spectator:
            room.record(
                "presence",
                {"kind": "join", "user": peer.user, "name": peer.name, "label": join.label,
                 "streams": streams, "rate": rate},
                now,
            )  # fmt: skip

    def _introduce(self, peer: Peer, member: Member, room: Room) -> None:
        """Tell a joining member about every member of ``room``, and every member about it
        (spectators excepted: nobody hears of them)."""
        spectators, send = self.spectators, self.relay.send
        for other in room.members.values():
            if other.user not in spectators:
                send(peer, Room.announce(other))
            if member.user not in spectators:
                other.presence.joined(Room.announce(member))  # at the room's next tick

    def leave(self, peer: Peer, now: float) -> None:
        """``peer``'s connection ended and it is not parked: it leaves its room."""
        room, user = peer.room, peer.user
        if room is not None and user is not None:
            relay = self.relay
            objects.owner_left(relay, room, user, now)
            room.remove(user)
            relay.rescheduled(room)
            spectator = user in self.spectators
            self.spectators.discard(user)
            if not spectator:
                room.record("presence", {"kind": "leave", "user": user, "reason": "left"}, now)
                for other in list(room.members.values()):
                    other.presence.left(PeerLeft(user=user, reason="left"))
            relay.forget_room_if_empty(room, now)
        peer.room = peer.member = None
