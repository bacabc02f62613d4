"""The relay, sans I/O: every rule of a posecast server, with no socket, task or clock.

:class:`RelayCore` is driven by its adapter (``server/app.py``) with what
happened and when: a connection opened (:meth:`~RelayCore.connect`), a frame
arrived (:meth:`~RelayCore.frame` then :meth:`~RelayCore.handle` for each
event it decodes to), a tick is due (:meth:`~RelayCore.tick`), the adapter can
write (:meth:`~RelayCore.take`), a connection ended
(:meth:`~RelayCore.disconnect`). Each call takes the time as an argument
(seconds on the server's monotonic clock; wall time only where an access token
is checked) and returns the :data:`Action` s the adapter must carry out, each
described where it is defined (``server.actions``): wake a connection's writer,
close it, look at the next tick or expiry again, write a record or a pose on a
room's recording, poll or finish a recording, hold an event for the adapter.

The parts of the core (``joins``, ``objects``, ``resume``, ``tokens``, ``capacity``)
see it through its port, ``server.ports.Relay``, which :class:`RelayCore` implements;
the table below says which part holds each rule.

The wire protocol (hello, join, the message state table, codes) is
:class:`protocol.ServerSession`'s; this module adds the relay's rules on top:

==================  ==========================================================
a connection ...    the relay ...
==================  ==========================================================
opens               over ``max_connections`` (or per source address): close
                    1013; not joined within ``join_timeout``: close 1008
                    (``server.joins``; closed at :meth:`~RelayCore.expire`)
says hello          takes a user id (u16, oldest-freed first), welcomes; over
                    its capacity (``server.capacity``; join too): ``server-full``
joins a room        (``server.joins``) normalises the name (NFC, stripped;
                    empty, over 64 bytes, control or bidi characters ->
                    ``bad-room``), checks the token (``secret`` set: HMAC,
                    room, expiry; refused -> ``unauthorized``, close 1008),
                    refuses over ``max_rooms``,
                    ``max_members`` or ``max_recorded_rooms`` (``room-full``),
                    creates the room on first join, allocates a stream id per
                    stream name, answers ``joined``, tells it every member
                    (``peer_joined``) and, at the room's next tick, every member
                    about it (``server.presence``); schedules it on its grid
publishes poses     admits at most ``max_update_rate`` updates and events a
                    second (a one-second token bucket; excess dropped and
                    counted, over ten seconds' worth closes 1008), keeps the
                    newest keyframe per stream by capture time (older: stale,
                    counted), taps the room's recorder; refuses (``bad-pose``,
                    counted, a drops record) an update captured over
                    ``max_capture_age`` ago, over ``max_capture_ahead`` ahead,
                    or with a position outside the room ``volume`` (stated
                    at welcome; compact codes quantise positions in it)
sends an event      the same bucket; relays it, in order, to every other
                    member; records it
asks a new rate     reschedules it (an emulated link's cap applies)
pings               answers with a pong stamped with the server time
sends bad data      answers ``error`` with the code; fatal ones close with
                    the code's close code (1002, 1008, 1009); each error or
                    refusal costs a token of its misbehaviour budget
                    (``misbehaviour_burst``, refilled ``misbehaviour_refill``
                    a second): none left closes 1008 "misbehaving"
says bye / leaves   closes 1000; the room hears ``peer_left`` at its next tick;
                    an empty room is removed and its recording finished
is too slow         latest-wins snapshots are skipped (counted) while one is
                    unsent or the socket holds over ``congested_bytes``;
                    overflowing the reliable queue (256) closes 1008 too-slow
stops publishing    after ``stall_after`` (1 s) with no accepted update, its
                    peers hear ``peer_stalled``; its next update brings
                    ``peer_resumed`` (``server.silence.Silence``)
==================  ==========================================================

A room (:class:`server.room.Room`) ticks each member on its own rate grid and
encodes one snapshot per tick group, shared by every due member. Shared objects
(their ownership rules and flights) are ``server/objects.py``'s.
"""

from __future__ import annotations

from posecast.protocol import (
    ROOM_USER,
    Bye,
    ErrorCode,
    ErrorMessage,
    Hello,
    Join,
    Limits,
    LocalProtocolError,
    ObjectCreate,
    Ping,
    Pong,
    PoseUpdate,
    ProtocolError,
    Release,
    Renew,
    RequestOwnership,
    SetRate,
    UserEvent,
    close_reason,
    encode_message,
)
from posecast.protocol.events import Event, Message
from posecast.server import capacity, objects, presence, rates, resume
from posecast.server.actions import (
    INFO,
    Action,
    Close,
    FinishRecording,
    Hold,
    Log,
    Rearm,
    Reschedule,
    Wake,
)
from posecast.server.config import ServerConfig
from posecast.server.guard import Guard
from posecast.server.handshakes import Handshakes
from posecast.server.joins import Joins
from posecast.server.limits import (
    Admission,
    error_message,
    update_refusal,
)
from posecast.server.link import Downlink
from posecast.server.member import IdAllocator, Member
from posecast.server.parking import Parking
from posecast.server.peer import COUNTERS, ConnectionStatistics, Peer
from posecast.server.ports import ClusterView
from posecast.server.room import TICK_LAG_BUCKETS, LagHistogram, Room
from posecast.server.rooms import RoomTable
from posecast.server.silence import Silence
from posecast.server.tokens import EVENT_TYPE, Tokens

__all__ = [
    "COUNTERS",
    "TICK_LAG_BUCKETS",
    "Action",
    "Close",
    "ConnectionStatistics",
    "FinishRecording",
    "Hold",
    "Log",
    "Peer",
    "Rearm",
    "RelayCore",
    "Reschedule",
    "ServerConfig",
    "Wake",
]


class RelayCore:
    """The relay's state and rules; see the module docstring for the protocol."""

    def __init__(self, config: ServerConfig | None = None) -> None:
        self.config = config or ServerConfig()
        self.limits = Limits(min_rate=self.config.min_rate, max_rate=self.config.max_rate)
        self.volume = self.config.room_volume
        self.users = IdAllocator(ROOM_USER)  # ROOM_USER is the shared objects' user id
        self.peers: dict[int, Peer] = {}
        self._by_user: dict[int, Peer] = {}
        self._next_conn = 0
        self._out: list[Action] = []
        self.closed_connections = 0
        #: Counters of connections that have ended, so that totals never go down.
        self.totals = dict.fromkeys(COUNTERS, 0)
        #: The rooms and their ticks (``server.rooms``); ``rooms`` is its dict of them.
        self.table = RoomTable(self.config, self.volume, self._out, objects.fly)
        self.rooms: dict[str, Room] = self.table.rooms
        self.table.adapt = rates.adapter(self)  # auto rates decide after each room's tick
        self.table.notify = presence.flusher(self.connected, self.send)  # once per tick
        cfg = self.config
        self.admission = Admission(cfg.max_connections, cfg.max_connections_per_address)
        self.handshakes = Handshakes(self.admission, guard=Guard.of(cfg))  # caps before handshake
        #: The cluster this relay is a node of (``server.node`` sets it; None: alone).
        self.cluster: ClusterView | None = None
        #: Members of dropped resumable connections, kept for ``resume_window``.
        self.parking = Parking(cfg.resume_window)
        self.capacity = capacity.Capacity(capacity.budget_of(cfg))  # sheds joins over budget
        #: Members whose updates stopped (``stall_after``): peers hear peer_stalled.
        self.silence = Silence(cfg.stall_after, self.tell_peers, self.emit_rearm)
        #: Recordings that stopped writing (disk full, I/O error), counted by the adapter.
        self.recording_errors = 0
        #: Connections refused (over a limit), closed for not joining in time, and
        #: closed for misbehaving (over their budget).
        self.refused_connections = self.join_timeouts = self.misbehaviour_closes = 0
        #: Access tokens: checked at join, renewed, expired; join and event rates.
        self.tokens = Tokens(self, self.peers)
        #: Admission, the join deadline, joins and leaves (``server.joins``).
        self.joins = Joins(self, self.peers, self.table, self.capacity, self.admission, self.tokens)
        self._spectators = self.joins.spectators  # (read on every update)

    @property
    def token_expiries(self) -> int:
        """Connections closed because their access token expired (a metric)."""
        return self.tokens.expiries

    @property
    def tick_lags(self) -> LagHistogram:
        """Every room's member ticks by lag (``posecast_tick_lag_seconds``)."""
        return self.table.tick_lags

    @property
    def tick_lag_counts(self) -> list[int]:
        """Member ticks per lag bucket (``TICK_LAG_BUCKETS``, then +Inf)."""
        return self.tick_lags.counts

    @property
    def tick_lag_sum(self) -> float:
        """The sum of those lags (s)."""
        return self.tick_lags.total

    # -- plumbing ----------------------------------------------------------------

    def emit(self, action: Action) -> None:
        """Queue an action for the caller (used by outboxes and rooms)."""
        self._out.append(action)

    def _note(self, line: Log | None) -> None:
        """A peer's log line, if it was not held back (``Peer.log``)."""
        if line is not None:
            self._out.append(line)

    def _actions(self) -> list[Action]:
        out = self._out  # (one list for good: the room table and rooms append to it)
        if not out:
            return []
        taken = out.copy()
        out.clear()
        return taken
        return out

    def pending(self) -> list[Action]:
        """Actions decided by :meth:`take` (the link's rate adaptation: ``Reschedule``)."""
        return self._actions()

    def peer(self, conn: int) -> Peer:
        return self.peers[conn]

    def peer_of(self, user: int) -> Peer:
        return self._by_user[user]

    def connected(self, user: int) -> Peer | None:
        """The live connection of ``user`` (None: none, e.g. it is parked)."""
        return self._by_user.get(user)

    def bind_user(self, user: int, peer: Peer) -> None:
        """``user`` is ``peer``'s from its hello on."""
        self._by_user[user] = peer

    def is_spectator(self, user: int | None) -> bool:
        """Whether ``user`` joined as a spectator (publishes nothing, unannounced)."""
        return self.joins.is_spectator(user)

    def new_conn(self) -> int:
        """A new connection id (also for parked members no socket holds)."""
        self._next_conn += 1
        return self._next_conn

    # -- connections ---------------------------------------------------------------

    def connect(self, now: float, address: str | None = None) -> int:
        """A new connection from ``address``; returns its id.

        Over ``max_connections`` (or ``max_connections_per_address``) it is closed
        at once with 1013 "try again later" (the ``Close`` is in :meth:`pending`).
        """
        conn = self.new_conn()
        peer = self.peers[conn] = Peer(conn, self, now, address)
        refused = self.joins.admit(peer, now)
        if refused is not None:
            self.refused_connections += 1
            self.emit(Log(INFO, "connection from %s refused: %s", (address, refused)))
            self.close_peer(peer, 1013, f"try again later: {refused}")
        return conn

    def buffered(self, conn: int, unsent: int) -> None:
        """Connection ``conn``'s socket holds ``unsent`` bytes not yet sent (the adapter
        tells whenever the number may have changed before a tick reads it): over
        ``congested_bytes`` its snapshots are skipped; auto rates read it too."""
        peer = self.peers.get(conn)
        if peer is not None:
            peer.outbox.buffered = unsent

    def next_expiry(self) -> float | None:
        """When the next connection is due to be closed (one that has not joined in
        time, or whose access token expires), or a publisher may have gone silent
        (None: none)."""
        due = [
            self.joins.next_deadline(),
            self.tokens.next_deadline(),
            self.parking.next(),
            self.silence.next(),
        ]
        return min((t for t in due if t is not None), default=None)

    def expire(self, now: float) -> list[Action]:
        """Close (1008) every connection not joined ``join_timeout`` after it opened,
        and every connection whose access token expired without a renew; announce
        every publisher whose updates stopped ``stall_after`` ago (``peer_stalled``)."""
        for conn in self.joins.unjoined(now):
            self.join_timeouts += 1
            self.close_peer(
                self.peers[conn], 1008, f"no join within {self.config.join_timeout:g} s"
            )
        self.tokens.expire(now)
        for parked in self.parking.expire(now):
            resume.gone(self, parked, now)
        self.silence.expire(now)
        return self._actions()

    def emit_rearm(self) -> None:
        """A deadline of :meth:`next_expiry` was added or moved."""
        self.emit(Rearm())

    def release_user(self, conn: int) -> None:
        """A forwarded ``conn`` whose room's node is gone: its user id is the room's
        again (the member restored from the lost node's records takes it)."""
        peer = self.peers.get(conn)
        if peer is not None and peer.forwarded and peer.user is not None:
            if self._by_user.get(peer.user) is peer:
                del self._by_user[peer.user]
            self.users.give_back(peer.user)
            peer.user = None

    def hand_off(self, conn: int) -> None:
        """``conn`` joins a room another cluster node owns (``server/forward.py``): this
        core handles nothing more of it; its user id stays taken until it ends."""
        peer = self.peers[conn]
        peer.forwarded, peer.resume_token = True, None

    def frame(self, conn: int, data: bytes | str, now: float | None = None) -> list[Event]:
        """The events one received frame decodes to (none while the connection closes;
        with ``now``, none for an event over its bucket: ``Tokens.event_dropped``)."""
        peer = self.peers[conn]
        if now is not None and self.tokens.event_dropped(peer, data, now):
            return []
        peer.frames_in += 1
        if peer.close_request is not None:
            # Closing: what it still sends cannot matter to anyone.
            peer.bytes_in += len(data)
            return []
        if isinstance(data, str):
            peer.bytes_in += len(data.encode())
            return [ProtocolError(ErrorCode.BAD_FRAME, "text frames are not allowed")]
        peer.bytes_in += len(data)
        return peer.session.receive_data(data)

    def room_to_open(self, conn: int, event: Event, wall: float) -> str | None:
        """The room a recording server must open (off the loop) before ``event``
        (``server.joins``)."""
        return self.joins.room_to_open(event, wall)

    def hold(self, conn: int, event: Event, wall: float) -> Hold | None:
        """Whether ``event`` of ``conn`` must wait before :meth:`handle` (None: it need
        not): a join for a cluster claim or a recording to open, a hello for the
        cluster's resume lookup (``server.joins.Joins.hold``). The adapter holds the
        connection's reads meanwhile (in order)."""
        return self.joins.hold(conn, event, wall, self.cluster)

    def unhold(self, conn: int) -> None:
        """The adapter is done holding ``conn`` (:meth:`hold`) and hands the held event
        to :meth:`handle` next; until then its join deadline does not close it."""
        self.joins.unhold(conn)

    def handle(self, conn: int, event: Event, now: float, wall: float = 0.0) -> list[Action]:
        """Apply one decoded event of connection ``conn``."""
        peer = self.peers.get(conn)
        if peer is not None:
            self._handle(peer, event, now, wall)
        return self._actions()

    def receive(self, conn: int, data: bytes | str, now: float, wall: float = 0.0) -> list[Action]:
        """:meth:`frame` and :meth:`handle` in one (rooms of a recording server must exist)."""
        peer = self.peers.get(conn)
        if peer is not None and not (
            data[1:12] == EVENT_TYPE and self.tokens.event_dropped(peer, data, now)
        ):
            for event in self.frame(conn, data):
                self._handle(peer, event, now, wall)
        return self._actions()

    def take(self, conn: int, now: float) -> tuple[list[bytes], float | None]:
        """Frames to write now (events in order, then the snapshot), and when the
        emulated link delivers its next one (None: nothing in flight)."""
        peer = self.peers.get(conn)
        if peer is None:
            return [], None
        out: list[bytes] = []
        downlink = peer.downlink
        if downlink is not None:
            downlink.arrived(now, out)
        outbox = peer.outbox
        while True:
            data, is_snapshot = outbox.take_with_kind()
            if data is None:
                break
            if is_snapshot and downlink is not None:
                self._into_link(peer, downlink, data, now)
            else:
                out.append(data)
        next_at = None
        if downlink is not None:
            downlink.arrived(now, out)
            next_at = downlink.next_arrival()
        peer.frames_out += len(out)
        peer.bytes_out += sum(len(d) for d in out)
        return out, next_at

    def events_pending(self, conn: int) -> bool:
        """Whether reliable messages of ``conn`` wait to be written."""
        peer = self.peers.get(conn)
        return peer is not None and bool(peer.outbox.events)

    def close(self, conn: int, code: int, reason: str) -> list[Action]:
        """Close ``conn`` on the server's own decision (e.g. 1001 going away)."""
        peer = self.peers.get(conn)
        if peer is not None:
            self.close_peer(peer, code, reason)
        return self._actions()

    def disconnect(self, conn: int, now: float, said_bye: bool = False) -> list[Action]:
        """Connection ``conn`` has ended (``said_bye``: the client closed it, rather than
        the socket dropping): leave its room, or park it (``server.resume``)."""
        peer = self.peers.pop(conn, None)
        if peer is None:
            return self._actions()
        if said_bye:
            peer.resume_token = None
        stats = peer.statistics()  # before leaving: the member's counters go with it
        held = peer.log_limit.flush(now)
        if held:
            msg = "user %s: %d more of its errors not logged in the last %.1f s"
            self.emit(Log(INFO, msg, (peer.user, held, peer.log_limit.span)))
        if resume.parkable(self, peer):
            resume.park(self, peer, now)
        else:
            self.joins.leave(peer, now)
        if peer.parked is not None:  # resumed, never joined again: parked again
            resume.unclaim(self, peer.parked, now)
        self.joins.release(peer)
        if peer.user is not None:
            self._by_user.pop(peer.user, None)
            if not self.parking.holds(peer.user):
                self.users.give_back(peer.user)
        self.closed_connections += 1
        for key in COUNTERS:
            self.totals[key] += getattr(stats, key)
        return self._actions()

    # -- rooms and ticks (``server.rooms``) --------------------------------------------

    def add_room(self, name: str, recorded: bool, now: float) -> bool:
        """Create room ``name``, ``recorded`` (the adapter opened its recording); False if
        it exists already or may not be created (then the adapter closes the recording)."""
        return self.table.add(name, recorded, now)

    def room_for(self, name: str) -> Room:
        """Room ``name``, created if there is none."""
        return self.table.room_for(name)

    def next_deadline(self) -> float | None:
        """When the next room tick is due (None: no member anywhere)."""
        return self.table.next_deadline()

    def rescheduled(self, room: Room) -> None:
        """A member of ``room`` joined, left or changed its rate: its ticks moved."""
        self.table.rescheduled(room)

    def tick(self, now: float, limit: int | None = None) -> list[Action]:
        """Send a snapshot to every due member of every room; flush drop counts.

        ``limit``: tick at most that many rooms (the adapter ticks one room per
        reading of its clock, so each room's lag and snapshot time are its own).
        Each due member's lag behind its due time goes into ``tick_lags``.
        A room whose tick fails (a bug) is removed and its members closed with
        1011; the other rooms go on.
        """
        for room in self.table.tick(now, limit):
            for member in list(room.members.values()):
                peer = self._by_user.get(member.user)
                if peer is not None:
                    self.close_peer(peer, 1011, "internal-error: room failed")
        return self._actions()

    def forget_room_if_empty(self, room: Room, now: float) -> None:
        """Remove ``room`` once its last member is gone (its recording is finished)."""
        self.table.forget_if_empty(room, now)

    def close_rooms(self, now: float) -> list[Action]:
        """Server shutdown: forget every room; recorded ones are to be finished."""
        self.table.close_all(now)
        return self._actions()

    @property
    def recording_paused(self) -> bool:
        """Pose updates are not recorded while set (see :meth:`pause_recording`)."""
        return self.table.recording_paused

    def pause_recording(self, now: float) -> list[Action]:
        """Stop recording pose updates in every room, and in rooms opened later."""
        self.table.pause_recording(now)
        return self._actions()

    def resume_recording(self, now: float) -> list[Action]:
        """Record pose updates again after :meth:`pause_recording`."""
        self.table.resume_recording(now)
        return self._actions()

    # -- statistics ---------------------------------------------------------------------

    def connection_statistics(self) -> list[ConnectionStatistics]:
        return [p.statistics() for p in self.peers.values()]

    # -- the rules -------------------------------------------------------------------------

    def to_member(self, member: Member, message: Message) -> None:
        """Send to a member's connection; a parked member (``server.resume``) keeps
        events for its resume and misses presence notices (it gets the room anew)."""
        peer = self._by_user.get(member.user)
        if peer is not None and not member.parked:
            for notice in member.presence.take_user(getattr(message, "user", None)):
                self.send(peer, notice)  # a peer's pending presence goes before news of it
            self.send(peer, message)
        elif isinstance(message, UserEvent):
            member.outbox.offer_event(encode_message(message))  # (no socket to wake)

    def tell_peers(self, room: Room, member: Member, notice: Message) -> None:
        """Queue ``notice`` (about ``member``) to every other member but spectators."""
        for other in list(room.members.values()):
            if other.user != member.user and other.user not in self._spectators:
                self.to_member(other, notice)

    def send(self, peer: Peer, message: Message) -> None:
        """Queue a reliable message; overflow closes that connection, not others.

        A message the session may no longer carry (it ended on a fatal error or
        bye) is dropped.
        """
        if peer.close_request is not None:
            return
        try:
            data = peer.session.send(message)
        except LocalProtocolError as exc:
            self.emit(Log(INFO, "user %s: not sent (%s)", (peer.user, exc)))
            return
        if peer.outbox.offer_event(data):
            self._out.append(Wake(peer.conn))
        else:
            peer.event_drops += 1
            self.close_peer(
                peer,
                ErrorCode.TOO_SLOW.close_code or 1008,
                f"too-slow: event queue overflow ({peer.outbox.max_events})",
            )

    def close_peer(self, peer: Peer, code: int, reason: str) -> None:
        if peer.close_request is None:
            peer.close_request = (code, close_reason(reason))
            self.emit(Close(peer.conn, *peer.close_request))

    def _protocol_error(self, peer: Peer, err: ProtocolError, now: float) -> None:
        peer.protocol_errors += 1
        self._note(peer.log(now, "user %s: %s (%s)", peer.user, err.message, err.code))
        self.send(peer, error_message(err))
        if err.fatal:
            self.close_peer(peer, err.close_code or 1002, err.close_reason)
        self._misbehaved(peer, now)

    def _misbehaved(self, peer: Peer, now: float) -> None:
        """Charge the misbehaviour budget one token; over it, close 1008."""
        if not peer.budget.spend(now) and peer.close_request is None:
            self.misbehaviour_closes += 1
            self.emit(Log(INFO, "user %s: over its misbehaviour budget, closing", (peer.user,)))
            self.close_peer(peer, 1008, "misbehaving: too many invalid frames")

    def refuse(
        self, peer: Peer, code: ErrorCode, message: str, what: str, now: float, charge: bool = True
    ) -> None:
        """Answer a refused ``what`` (join, update) with a non-fatal error; charge the budget."""
        self._note(peer.log(now, "user %s: %s refused: %s (%s)", peer.user, what, message, code))
        self.send(peer, error_message(code, message, what))
        if charge:
            self._misbehaved(peer, now)

    def _handle(self, peer: Peer, event: Event, now: float, wall: float) -> None:
        if isinstance(event, PoseUpdate | UserEvent) and peer.user in self._spectators:
            what = "event" if isinstance(event, UserEvent) else "update"
            event = ProtocolError(ErrorCode.STREAM_NOT_OWNED, "spectators publish nothing", what)
        if isinstance(event, Hello | Join) and self.capacity.shed(self, peer, event, now):
            return
        if isinstance(event, PoseUpdate):
            self._on_update(peer, event, now)
        elif isinstance(event, Ping):
            self.send(peer, Pong(seq=event.seq, ping_time=event.time, recv_time=now, send_time=now))
        elif isinstance(event, ProtocolError):
            self._protocol_error(peer, event, now)
        elif isinstance(event, Hello):
            resume.hello(self, peer, event, now)
        elif isinstance(event, Join):
            self.joins.join(peer, event, now, wall)
        elif isinstance(event, SetRate):
            self._on_set_rate(peer, event, now)
        elif isinstance(event, Renew):
            self.tokens.renew(peer, event, now, wall)
        elif isinstance(event, UserEvent):
            self._on_user_event(peer, event, now)
        elif isinstance(event, ObjectCreate | RequestOwnership | Release):
            objects.handle(self, peer, event, now)
        elif isinstance(event, Bye):
            self.close_peer(peer, 1000, event.reason or "bye")
        elif isinstance(event, ErrorMessage):
            self._note(
                peer.log(now, "user %s reports %s: %s", peer.user, event.code, event.message)
            )
            if event.fatal:
                # Its session is over (CLOSED): nothing more may be sent to it.
                self.close_peer(peer, 1000, f"client ended the session: {event.code}")

    def _on_set_rate(self, peer: Peer, event: SetRate, now: float) -> None:
        room, user = peer.room, peer.user
        if room is None or user is None:
            return
        if peer.member is not None:  # a rate asked is no auto rate any more
            peer.member.asked_rate, peer.member.link_rate = event.rate, None
        rate = event.rate if peer.downlink is None else peer.downlink.rate_for(event.rate)
        room.set_rate(user, max(self.config.min_rate, rate), now)
        self.rescheduled(room)
        room.record("presence", {"kind": "rate", "user": user, "rate": event.rate}, now)

    def _on_user_event(self, peer: Peer, event: UserEvent, now: float) -> None:
        room = peer.room
        if room is None or not self.tokens.admit_event(peer, now):
            return
        for m in list(room.members.values()):
            if m.user != peer.user:
                self.to_member(m, event)
        if room.recorded:
            room.record(
                "event",
                {
                    "kind": event.kind,
                    "user": event.user,
                    "stream": event.stream,
                    "time": event.time,
                    "payload": event.payload,
                },
                now,
            )

    def admit_update(self, peer: Peer, now: float) -> bool:
        """The update bucket (:meth:`Peer.admit`); a connection that keeps flooding is closed."""
        rate = self.config.max_update_rate
        if peer.admit(rate, now):
            return True
        if peer.flood_drops > 10 * rate:
            self.close_peer(peer, 1008, f"update flood: over {rate:g} updates/s")
        return False

    def _on_update(self, peer: Peer, update: PoseUpdate, now: float) -> None:
        room, user = peer.room, peer.user
        if self.admit_update(peer, now) and room is not None and user is not None:
            cfg = self.config
            age = cfg.max_capture_age + self.capacity.late  # the relay's own lag is no age
            refused = update_refusal(update, now, age, cfg.max_capture_ahead, self.volume)
            if refused is not None:
                peer.count_refused(refused.kind)
                room.note_drop(refused.kind, user)
                aged = refused.kind == "stale-capture"  # never charged; one error a second
                if not aged or capacity.stale_error_due(peer, now):
                    self.refuse(peer, ErrorCode.BAD_POSE, refused.message, "update", now, not aged)
                return
            update = peer.stamps.check(update, now)  # a lagging liar's are moved (stamps.py)
            stale = room.ingest(user, update, peer.session.compact_codes())
            if peer.member is not None:
                self.silence.updated(room, peer.member, now)
            if room.recorded:
                if room.recording_paused:
                    room.paused_updates += 1
                    return
                room.record_pose(user, now, update, peer.session.compact_codes())
                if stale:
                    room.note_drop("stale", user, stale)

    def _into_link(self, peer: Peer, downlink: Downlink, data: bytes, now: float) -> None:
        """Put a snapshot on the emulated link; adopt the rate its cap allows."""
        room, member = peer.room, peer.member
        if not downlink.send(now, data) and member is not None:
            member.undelivered()  # the link lost or skipped it: never a baseline
        if room is not None and member is not None and member.link_rate is None:
            rate = max(self.config.min_rate, downlink.rate_for(member.asked_rate))
            if abs(rate - member.rate) > 0.25:
                room.set_rate(member.user, rate, now)
                self.rescheduled(room)
