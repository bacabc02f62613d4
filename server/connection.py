"""One websocket as the relay runs it: the per-connection half of the asyncio adapter.

A :class:`Connection` is an :class:`asyncio.Protocol` on the loop's transport
(``server/transport.py``, websockets' sans-I/O protocol inside) bound to one
connection of the core (``server/core.py``). It carries out the core's decisions for
that connection and decides nothing itself:

- **reading**: the messages of one read are fed to the core in one go, with one
  clock reading, each event's actions carried out before the next event (pose
  updates cause none). A join the core holds (``RelayCore.hold``: a recording to
  open, a cluster claim, a resume lookup) stops the reads until it is done, then
  they go on in order; a client whose room another cluster node owns has its
  frames forwarded there from then on.
- **writing**: a ``Wake`` is carried out at once (``RelayCore.take``, then
  ``transport.write``); each payload is framed once and the framed bytes written to
  every subscriber that gets the same payload (:class:`Framer`). While the
  transport's buffer is full (``pause_writing``) nothing is taken: reliable
  messages wait in the outbox, whose bound the core enforces, and the latest-wins
  snapshot slot keeps the newest. An emulated link's delayed frames are written by
  one timer per connection at most.
- **closing**: ``Close`` writes the queued messages (the error that explains the
  close) first, waiting at most 0.5 s for a full buffer to drain, then starts the
  closing handshake, bounded by ``close_timeout``, then aborts.

The server it runs under (``server/app.py``'s ``RelayServer``) is seen only as a
:class:`Host`: its public methods and fields.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable, Coroutine, Iterator
from typing import TYPE_CHECKING, Any, Protocol

from websockets.http11 import Request, Response
from websockets.protocol import State as WsState
from websockets.server import ServerProtocol

from posecast.protocol import Limits
from posecast.protocol.events import Event
from posecast.server.actions import Action, Hold
from posecast.server.config import ServerConfig
from posecast.server.handshakes import Slot
from posecast.server.http import OriginPolicy, QuietHttpLog
from posecast.server.member import Outbox
from posecast.server.peer import ConnectionStatistics
from posecast.server.transport import WebSocketConnection, frame_binary

if TYPE_CHECKING:
    from posecast.server.core import RelayCore
    from posecast.server.node import ClusterNode

__all__ = ["DRAIN_BEFORE_CLOSE", "FORWARDED_BUFFER", "OPEN_TIMEOUT", "Connection", "Framer", "Host"]

#: How long a Close waits for a full write buffer to take the queued messages.
DRAIN_BEFORE_CLOSE = 0.5
#: An opening handshake not finished this long after the TCP connection is dropped
#: (the default of ``ServerConfig.handshake_timeout``; it was 10 s).
OPEN_TIMEOUT = 2.0
#: A forwarded client (its room is another cluster node's) with more than this
#: unsent is closed as too slow: the owner node cannot see its socket's buffer.
FORWARDED_BUFFER = 1 << 20


class Framer:
    """Frame once, write many: the last payload framed, and its websocket frame."""

    __slots__ = ("framed", "source")

    def __init__(self) -> None:
        self.source: bytes | None = None
        self.framed = b""

    def frame(self, data: bytes) -> bytes:
        """``data`` as a binary frame; the same payload object gives the same bytes."""
        if data is self.source:
            return self.framed
        self.source, self.framed = data, frame_binary(data)
        return self.framed


class Host(Protocol):
    """What a connection uses of the server it runs under (``app.RelayServer``)."""

    config: ServerConfig
    limits: Limits
    core: RelayCore
    clock: Callable[[], float]
    wall_clock: Callable[[], float]
    cluster: ClusterNode | None
    http: Callable[[ServerProtocol, Request], Response | None]
    origins: OriginPolicy
    ws_log: QuietHttpLog
    frames: Framer
    #: Connections whose sockets held unsent bytes when last told (``tell_unsent``).
    unsent: set[Connection]

    @property
    def closing(self) -> bool:
        """stop() has begun: handshakes from then on get a 503."""
        ...

    @property
    def stopping(self) -> bool:
        """stop() was called."""
        ...

    def apply(self, actions: list[Action]) -> None:
        """Carry out the core's actions."""
        ...

    def spawn(self, job: Coroutine[Any, Any, None], name: str) -> None:
        """Run ``job`` under the server's task group."""
        ...

    async def prepare_room(self, name: str) -> None:
        """Make sure room ``name`` exists, its recording open."""
        ...

    def socket_opened(self, conn: Connection) -> None:
        """A TCP connection was accepted (handshake or not)."""
        ...

    def socket_gone(self, conn: Connection) -> None:
        """A TCP connection has ended."""
        ...

    def opened(self, conn: Connection, actions: list[Action]) -> None:
        """``conn``'s handshake is done and the core knows it: carry out ``actions``."""
        ...

    def serves(self, conn: Connection) -> bool:
        """Whether ``conn`` is still one of the server's open websockets."""
        ...

    def ended(self, conn: Connection) -> None:
        """``conn``'s websocket has ended."""
        ...


class Connection(WebSocketConnection):
    """One websocket as the relay runs it: the core's connection ``conn`` on a transport."""

    def __init__(self, server: Host) -> None:
        cfg = server.config
        super().__init__(
            max_size=server.limits.max_frame_size,
            ping_interval=cfg.ping_interval or None,
            ping_timeout=cfg.ping_timeout or None,
            close_timeout=cfg.close_timeout,
            open_timeout=cfg.handshake_timeout or OPEN_TIMEOUT,
            logger=server.ws_log,
        )
        self.server = server
        self.conn = 0
        self.close_request: tuple[int, str] | None = None
        self._drain_timer: asyncio.TimerHandle | None = None
        self._link_timer: asyncio.TimerHandle | None = None
        self._link_at = 0.0
        #: Set while a recorded room opens for a join: the reads after it wait here.
        self._held = False
        self._backlog: list[bytes | str] = []
        #: In a cluster: its room is another node's, its frames are forwarded there.
        self.forwarded = False
        #: Its place before the handshake (``server/handshakes.py``; None: none held).
        self._slot: Slot | None = None
        self._address: str | None = None
        self._joining = True  # (not a member yet: its reads are ``Capacity.join_work``)
        #: The unsent bytes the core was last told (``tell_unsent``).
        self._told = 0

    @property
    def outbox(self) -> Outbox:
        return self.server.core.peer(self.conn).outbox

    @property
    def user(self) -> int | None:
        return self.server.core.peer(self.conn).user

    def statistics(self) -> ConnectionStatistics:
        return self.server.core.peer(self.conn).statistics()

    def buffered(self) -> int:
        return int(self.transport.get_write_buffer_size())

    def tell_unsent(self) -> None:
        """Tell the core the socket's unsent bytes if they changed since it was last told.

        Only a write adds to them (told after each ``flush``); the loop sends them
        between callbacks, so a connection with some left stays in the server's
        ``unsent`` set, told again before each tick: a room's tick reads a number."""
        n = self.buffered()
        if n != self._told:
            self._told = n
            self.server.core.buffered(self.conn, n)
        if n:
            self.server.unsent.add(self)
        else:
            self.server.unsent.discard(self)

    # -- the websocket's hooks ---------------------------------------------------------------

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        super().connection_made(transport)
        self.server.socket_opened(self)
        peername = transport.get_extra_info("peername")
        self._address = peername[0] if isinstance(peername, tuple) and peername else None
        shakes = self.server.core.handshakes
        self._slot = shakes.admit(self._address, self.server.clock(), key=self)
        for oldest in shakes.take_evicted():  # at the cap: slow handshakes give way
            if isinstance(oldest, Connection):
                oldest.abort()
        logs: list[Action] = [*shakes.take_logs()]
        if logs:
            self.server.apply(logs)
        if self._slot is None:
            self.abort()  # over the caps and the spare places: not one byte read

    def _release_slot(self) -> None:
        if self._slot is not None:
            self.server.core.handshakes.release(self._slot, self._address, key=self)
            self._slot = None

    def data_received(self, data: bytes) -> None:
        if not self._joining:  # a member's read: the steady work
            return self._read(data)
        server, cpu, start = self.server, time.process_time(), self.server.clock()
        self._read(data)
        server.core.capacity.join_work(start, server.clock(), time.process_time() - cpu)
        peer = server.core.peers.get(self.conn)  # (a forwarded client is in another node's room)
        self._joining = not self.forwarded and (peer is None or peer.room is None)

    def _read(self, data: bytes) -> None:
        """The transport parses ``data``; this hands its messages on (no call back up)."""
        messages = self.read(data)
        if messages:
            try:
                self.on_messages(messages)
            except Exception:
                self.read_failed()

    def connection_lost(self, exc: Exception | None) -> None:
        for timer in (self._drain_timer, self._link_timer):
            if timer is not None:
                timer.cancel()
        if self._slot is not None and self.handshake_expired:
            self.server.core.handshakes.timeouts += 1
        self._release_slot()
        try:
            super().connection_lost(exc)
        finally:
            self.server.socket_gone(self)

    def on_request(self, request: Request) -> Response | None:
        server = self.server
        response = server.http(self.protocol, request)
        if response is None and server.closing:
            return self.protocol.reject(503, "Service Unavailable: the relay is stopping\n")
        if response is None:
            origins = request.headers.get_all("Origin")
            if len(origins) > 1:
                return self.protocol.reject(400, "Bad Request: more than one Origin header\n")
            refused = server.origins.refusal(origins[0] if origins else None)
            if refused is not None:
                return self.protocol.reject(403, f"Forbidden: {refused}\n")
        return response

    def on_open(self) -> None:
        server, core = self.server, self.server.core
        over = self._slot == "probe"  # a spare place: over a cap before its handshake
        self._release_slot()  # counted by the core from now on
        self.conn = core.connect(server.clock(), self._address)
        self.tell_unsent()  # (the handshake's response may still be unsent)
        self.pongs = core.peers[self.conn].stamps.round_trip  # its round trips (stamps.py)
        # Refused over a connection limit (a Close), or a join deadline to watch.
        server.opened(self, core.pending())
        if over and core.peer(self.conn).close_request is None:
            core.refused_connections += 1
            server.apply(core.close(self.conn, 1013, "try again later: too many connections"))
        if server.stopping:
            # Its handshake finished after stop() had closed the others. Through the
            # core, which then handles nothing more it sends (no hello, no join).
            server.apply(core.close(self.conn, 1001, "going away"))

    def on_messages(self, messages: list[bytes | str]) -> None:
        if self._held:  # (reading is paused; what was read already waits its turn)
            self._backlog.extend(messages)
            return
        server = self.server
        if self.forwarded:
            assert server.cluster is not None
            if not server.cluster.edge.forward(self.conn, messages):
                self.close(1013, "try again later: the cluster is not taking frames")
            return
        if server.config.record_dir is not None or server.cluster is not None:
            self._consume([], iter(messages))
            return
        # No room to open first: each message straight through the core (one event
        # each, as a rule), its actions carried out before the next one.
        receive, apply, conn = server.core.receive, server.apply, self.conn
        now, wall = server.clock(), server.wall_clock()
        for data in messages:
            actions = receive(conn, data, now, wall)
            if actions:
                apply(actions)

    def on_writable(self) -> None:
        self.flush()
        if self.close_request is not None and not self.server.core.events_pending(self.conn):
            self._close_now()

    def on_end(self) -> None:
        server = self.server
        server.ended(self)
        # A close frame from the client is a goodbye; a dropped socket may resume.
        said_bye = self.protocol.close_rcvd is not None
        if self.forwarded and server.cluster is not None:
            server.cluster.edge.gone(self.conn, said_bye)
        server.apply(server.core.disconnect(self.conn, server.clock(), said_bye))

    # -- reading -----------------------------------------------------------------------------

    def _consume(
        self, events: list[Event], messages: Iterator[bytes | str], raw: bytes | str = b""
    ) -> None:
        """Feed ``events``, then each of ``messages``, to the core, with one clock reading.

        The actions of each event are carried out before the next event: a burst of
        relayed events in one read must reach the peers' sockets one by one, so that
        their bounded queues measure how slow *they* are, not how many events this
        read held (pose updates cause no action: the batch costs nothing for them).
        A join that opens a recorded room stops here: the room opens off the loop
        (``_open_then_consume``), and the rest follows in order once it is open. In
        a cluster, so does a join of a room this node does not own: the room is
        claimed first (``_claim_then_consume``). ``raw``: the frame ``events`` came in.
        """
        server, core, conn = self.server, self.server.core, self.conn
        now, wall = server.clock(), server.wall_clock()
        apply = server.apply
        skip_check = bool(events)  # the held event's room was just opened
        while True:
            for i, event in enumerate(events):
                if not (skip_check and i == 0):
                    held = core.hold(conn, event, wall)
                    if held is not None:
                        self._hold(held, events[i:], messages, raw)
                        return
                actions = core.handle(conn, event, now, wall)
                if actions:
                    apply(actions)
            skip_check = False
            data = next(messages, None)
            if data is None:
                return
            events, raw = core.frame(conn, data, now), data

    def _hold(
        self, held: Hold, events: list[Event], rest: Iterator[bytes | str], raw: bytes | str
    ) -> None:
        """Stop reading until the core's ``held`` is done (the room open, or claimed in
        the cluster, or the member resumable with its token found); then go on in order."""
        self._held = True
        self._backlog = list(rest)
        self.transport.pause_reading()
        if held.kind == "resume":
            assert held.token is not None
            job = self._resume_then_consume(held.token, events, raw)
        elif held.kind == "claim":
            job = self._claim_then_consume(held.room, events, raw)
        else:
            job = self._open_then_consume(held.room, events)
        self.server.spawn(job, f"open:{held.room}")

    def write_forwarded(self, data: bytes) -> None:
        """Write a frame the room's owner node sent this (forwarded) client."""
        if self.protocol.state is not WsState.OPEN or self.close_request is not None:
            return
        server = self.server
        if self.buffered() > FORWARDED_BUFFER:
            self.close(1008, "too-slow: the client does not read its frames")
            return
        self.transport.write(server.frames.frame(data))

    async def _open_then_consume(self, room: str, events: list[Event]) -> None:
        if room:
            await self.server.prepare_room(room)
        if not self.server.serves(self):
            return  # it ended meanwhile
        self.server.core.unhold(self.conn)
        backlog, self._held = self._backlog, False
        self._backlog = []
        self._consume(events, iter(backlog))
        if not self._held:
            self.transport.resume_reading()

    async def _claim_then_consume(self, room: str, events: list[Event], raw: bytes | str) -> None:
        """Claim ``room`` in the cluster; join here if this node owns it now, else hand
        the connection off to its owner, the join frame first."""
        cluster = self.server.cluster
        assert cluster is not None
        owner = await cluster.place_join(room)
        if not self.server.serves(self):
            return  # it ended meanwhile
        if owner is None:
            self.close(1013, "try again later: the cluster cannot place the room")
        elif owner == cluster.name:
            await self._open_then_consume(room, events)
        else:
            self._forward(owner, raw)

    async def _resume_then_consume(self, token: str, events: list[Event], raw: bytes | str) -> None:
        """A hello resuming a member this node does not hold: resume here if this node
        owns its room now, else hand the connection to the owner, the hello first."""
        cluster = self.server.cluster
        assert cluster is not None
        placed = await cluster.place_resume(token)
        if not self.server.serves(self):
            return
        if placed is not None and placed[0] != cluster.name:
            self._forward(placed[0], raw, placed[1])
        else:
            await self._open_then_consume("", events)

    def _forward(self, owner: str, raw: bytes | str, resumes: int | None = None) -> None:
        """From now on this connection's frames go to node ``owner``, ``raw`` first."""
        cluster = self.server.cluster
        assert cluster is not None
        backlog, self._held, self._backlog = self._backlog, False, []
        where = self._address or "?"
        self.forwarded = True
        frames = [raw, *backlog]
        if resumes is None:
            ok = cluster.hand_off(self.conn, owner, where, frames)
        else:
            ok = cluster.hand_off_resume(self.conn, owner, resumes, where, frames)
        if not ok:
            self.close(1013, "try again later: the cluster is not taking frames")
            return
        self.transport.resume_reading()

    # -- writing -----------------------------------------------------------------------------

    def flush(self) -> None:
        """Write what the core has for this connection now (unless the buffer is full)."""
        if self.paused or self.protocol.state is not WsState.OPEN:
            return
        server = self.server
        core = server.core
        frames, next_at = core.take(self.conn, server.clock())
        if frames:
            write, frame = self.transport.write, server.frames.frame
            for data in frames:
                write(frame(data))  # the same payload object: the same framed bytes
            if self.transport.get_write_buffer_size() or self._told:
                self.tell_unsent()
        if next_at is not None:
            self._link_due(next_at)
        pending = core.pending()
        if pending:  # the link's rate adaptation may have moved a tick earlier
            server.apply(pending)

    def _link_due(self, at: float) -> None:
        """The emulated link delivers its next frame at ``at``: one timer, the earliest."""
        timer = self._link_timer
        if timer is not None:
            if self._link_at <= at:
                return
            timer.cancel()
        self._link_at = at
        delay = max(0.0, at - self.server.clock())
        self._link_timer = asyncio.get_running_loop().call_later(delay, self._link_fire)

    def _link_fire(self) -> None:
        self._link_timer = None
        self.flush()

    # -- closing -----------------------------------------------------------------------------

    def close(self, code: int, reason: str) -> None:
        """Write the queued messages (waiting at most 0.5 s for the buffer), then close."""
        if self.close_request is not None:
            return
        self.close_request = (code, reason)
        self.flush()
        if self.server.core.events_pending(self.conn):
            loop = asyncio.get_running_loop()
            self._drain_timer = loop.call_later(DRAIN_BEFORE_CLOSE, self._close_now)
        else:
            self._close_now()

    def _close_now(self) -> None:
        if self._drain_timer is not None:
            self._drain_timer.cancel()
            self._drain_timer = None
        assert self.close_request is not None
        self.start_close(*self.close_request)
