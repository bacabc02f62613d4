"""The relay's asyncio adapter: sockets, timers and time around :class:`server.core.RelayCore`.

Every rule of the relay lives in the sans-I/O core (``server/core.py``: its
docstring is the protocol); this module only carries out what the core decides, with
no task and no Event per connection. Each websocket is one :class:`asyncio.Protocol`
on the loop's transport (``server/transport.py``, websockets' sans-I/O protocol
inside): the messages of one read are fed to the core in one go, with one clock
reading, each event's actions carried out before the next event (pose updates cause
none). Writes are driven by the core: a ``Wake`` is carried out at once
(:meth:`RelayCore.take`, then ``transport.write``), so after a room tick every due
subscriber's snapshot is written in that same callback; each payload is framed once
and the framed bytes written to every subscriber that gets the same payload (members
of one tick group get the very same ``bytes``). While the transport's buffer is full
(``pause_writing``) nothing is taken: reliable messages wait in the outbox, whose
bound the core enforces, and the latest-wins snapshot slot keeps the newest. An
emulated link's delayed frames are written by one timer per connection at most.
``Close`` writes the queued messages (the error that explains the close) first,
waiting at most 0.5 s for a full buffer to drain, then starts the closing handshake,
bounded by ``close_timeout``, then aborts.

One timer ticks the rooms: each due room is ticked at its own reading of the clock
(``RelayCore.tick(now, limit=1)``), so its lag and snapshot time are its own; each
tick's lag, the time spent on connections not yet members, and twice a second the
process's CPU time and the bytes unsent over all connections, go to the core's
capacity (``server/capacity.py``), which refuses members over its budget. One task
sleeps until :meth:`RelayCore.next_expiry` and closes the connections that have not
joined in time. Recordings open and close off the event loop (a connection whose join
opens a recorded room stops reading until the room is open). ``GET /healthz`` and
``GET /metrics`` are answered on the websocket port (``server/http.py``); a browser
page from an origin not in ``allow_origins`` is refused with 403 before its handshake.

Logging is sized for a server that runs for weeks: plain HTTP requests (health
probes, metrics scrapes, rejected handshakes) are logged at DEBUG, not at
websockets' INFO, and what a peer causes (its protocol errors, the errors it
reports) is logged at most once per ``ServerConfig.peer_log_interval`` per
connection, with a count of the records held back (:class:`LogLimiter`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import ssl
import time
from collections.abc import AsyncIterator, Callable, Coroutine, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from websockets.http11 import Request, Response
from websockets.protocol import State as WsState

from posecast.protocol import codec
from posecast.protocol.events import Event
from posecast.server.core import (
    Action,
    Close,
    ConnectionStatistics,
    FinishRecording,
    Hold,
    Rearm,
    RelayCore,
    Reschedule,
    ServerConfig,
    Wake,
)
from posecast.server.handshakes import Slot, fd_budget
from posecast.server.http import OriginPolicy, QuietHttpLog, metrics_text, process_request
from posecast.server.intake import Intake, measure
from posecast.server.logs import LogLimiter
from posecast.server.node import cluster_clock
from posecast.server.recordings import Recordings
from posecast.server.room import IdAllocator, Outbox, Room
from posecast.server.transport import WebSocketConnection, frame_binary

if TYPE_CHECKING:
    from posecast.server.node import ClusterNode

__all__ = ["ConnectionStatistics", "LogLimiter", "RelayServer", "ServerConfig", "serving"]

log = logging.getLogger("posecast.server")

Clock = Callable[[], float]

#: How long a Close waits for a full write buffer to take the queued messages.
DRAIN_BEFORE_CLOSE = 0.5
#: An opening handshake not finished this long after the TCP connection is dropped
#: (the default of ``ServerConfig.handshake_timeout``; it was 10 s).
OPEN_TIMEOUT = 2.0
#: A forwarded client (its room is another cluster node's) with more than this
#: unsent is closed as too slow: the owner node cannot see its socket's buffer.
FORWARDED_BUFFER = 1 << 20
#: Listen backlog: connections queued until accepted (past it dropped, to SYN retries).
ACCEPTS = 4096


class _Connection(WebSocketConnection):
    """One websocket as the relay runs it: the core's connection ``conn`` on a transport."""

    def __init__(self, server: RelayServer) -> None:
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

    @property
    def outbox(self) -> Outbox:
        return self.server.core.peer(self.conn).outbox

    @property
    def user(self) -> int | None:
        return self.server.core.peer(self.conn).user

    def statistics(self) -> ConnectionStatistics:
        return self.server.core.peer(self.conn).statistics()

    def _buffered(self) -> int:
        return int(self.transport.get_write_buffer_size())

    # -- the websocket's hooks ---------------------------------------------------------------

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        super().connection_made(transport)
        self.server._sockets.add(self)
        self.server._all_gone.clear()
        peername = transport.get_extra_info("peername")
        self._address = peername[0] if isinstance(peername, tuple) and peername else None
        shakes = self.server.core.handshakes
        self._slot = shakes.admit(self._address, self.server.clock(), key=self)
        for oldest in shakes.take_evicted():  # at the cap: slow handshakes give way
            if isinstance(oldest, _Connection):
                oldest.abort()
        if self._slot is None:
            self.abort()  # over the caps and the spare places: not one byte read

    def _release_slot(self) -> None:
        if self._slot is not None:
            self.server.core.handshakes.release(self._slot, self._address, key=self)
            self._slot = None

    def data_received(self, data: bytes) -> None:
        if not self._joining:  # a member's read: the steady work
            return super().data_received(data)
        server, cpu, start = self.server, time.process_time(), self.server.clock()
        super().data_received(data)
        server.core.capacity.join_work(start, server.clock(), time.process_time() - cpu)
        peer = server.core.peers.get(self.conn)  # (a forwarded client is in another node's room)
        self._joining = not self.forwarded and (peer is None or peer.room is None)

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
            self.server._socket_gone(self)

    def on_request(self, request: Request) -> Response | None:
        server = self.server
        response = server.http(self.protocol, request)
        if response is None and server._closing:
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
        self.conn = core.connect(server.clock(), self._buffered, self._address)
        self.pongs = core.peers[self.conn].stamps.round_trip  # its round trips (stamps.py)
        server._conns[self.conn] = self
        # Refused over a connection limit (a Close), or a join deadline to watch.
        server.apply(core.pending())
        server._new_connection.set()
        if over and core.peer(self.conn).close_request is None:
            core.refused_connections += 1
            server.apply(core.close(self.conn, 1013, "try again later: too many connections"))
        if server._stop.is_set():
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
        server._conns.pop(self.conn, None)
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
        if self._buffered() > FORWARDED_BUFFER:
            self.close(1008, "too-slow: the client does not read its frames")
            return
        if data is server._framed_src:
            self.transport.write(server._framed)
        else:
            framed = frame_binary(data)
            server._framed_src, server._framed = data, framed
            self.transport.write(framed)

    async def _open_then_consume(self, room: str, events: list[Event]) -> None:
        if room:
            await self.server.prepare_room(room)
        if self.server._conns.get(self.conn) is not self:
            return  # it ended meanwhile
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
        if self.server._conns.get(self.conn) is not self:
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
        if self.server._conns.get(self.conn) is not self:
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
            write = self.transport.write
            for data in frames:
                # Frame once, write many: the same payload object, the same bytes.
                if data is server._framed_src:
                    write(server._framed)
                else:
                    framed = frame_binary(data)
                    server._framed_src, server._framed = data, framed
                    write(framed)
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


class RelayServer:
    """The relay: ``await RelayServer(config).run()`` serves until :meth:`stop`."""

    def __init__(
        self,
        config: ServerConfig | None = None,
        clock: Clock = time.monotonic,
        wall_clock: Clock = time.time,
    ) -> None:
        self.config = config or ServerConfig()
        if self.config.cluster is not None and clock is time.monotonic:
            clock = cluster_clock()  # one time on every node
        self.clock = clock
        self.wall_clock = wall_clock
        self.core = RelayCore(self.config)
        self.limits = self.core.limits
        self._conns: dict[int, _Connection] = {}
        #: Every TCP connection, handshake or not (stop() waits for them all to end).
        self._sockets: set[_Connection] = set()
        self._all_gone = asyncio.Event()
        self._all_gone.set()
        self._tg: asyncio.TaskGroup | None = None
        #: Set when a connection opens: its join deadline may be the next expiry.
        self._new_connection = asyncio.Event()
        self._tick_timer: asyncio.TimerHandle | None = None
        self._tick_at = 0.0
        self._measure_at = 0.0
        self._intake: Intake | None = None  # (accepts what the loop has not, each tick)
        #: Frame once, write many: the last payload framed, and its frame.
        self._framed_src: bytes | None = None
        self._framed = b""
        #: The cluster side (``--cluster``), from run() on.
        self.cluster: ClusterNode | None = None
        self.http = process_request(self.core, self.clock, self._cluster_metrics)
        self.origins = OriginPolicy(self.config.allow_origins)
        self.ws_log = QuietHttpLog(logging.getLogger("websockets.server"), {})
        #: Recorders of the rooms (``--record``), opened and closed off the loop.
        self.recorders = Recordings(
            self.config,
            clock,
            wall_clock,
            self.core.add_room,
            self._recording_metadata,
            on_error=self._count_recording_error,
        )
        self._stop = asyncio.Event()
        #: Set once stop() has begun: handshakes from then on get a 503.
        self._closing = False
        self.ready = asyncio.Event()
        self.port: int | None = None

    # -- the core's state, as before ---------------------------------------------------

    @property
    def rooms(self) -> dict[str, Room]:
        return self.core.rooms

    @property
    def users(self) -> IdAllocator:
        return self.core.users

    @property
    def closed_connections(self) -> int:
        return self.core.closed_connections

    @property
    def totals(self) -> dict[str, int]:
        return self.core.totals

    def _count_recording_error(self) -> None:
        self.core.recording_errors += 1

    @property
    def recording_paused(self) -> bool:
        return self.core.recording_paused

    def connection_of(self, user: int) -> _Connection:
        return self._conns[self.core.peer_of(user).conn]

    # -- carrying out the core's decisions ------------------------------------------------

    def apply(self, actions: list[Action]) -> None:
        conns = self._conns
        for action in actions:
            if type(action) is Wake:
                conn = conns.get(action.conn)
                if conn is not None:
                    conn.flush()
                elif self.cluster is not None and action.conn in self.cluster.members.remote:
                    self.cluster.members.route([action])
            elif isinstance(action, Close):
                conn = conns.get(action.conn)
                if conn is not None:
                    conn.close(action.code, action.reason)
                elif self.cluster is not None and action.conn in self.cluster.members.remote:
                    self.cluster.members.route([action])
            elif isinstance(action, Reschedule):
                self._arm_ticks()
            elif isinstance(action, Rearm):
                self._new_connection.set()
            elif isinstance(action, FinishRecording):
                rec = self.recorders.take(action.room)
                if rec is not None:
                    self.spawn(self.recorders.finish(action.room, rec), f"close:{action.room}")
            else:  # Record, RecordPose, PollRecording
                self.recorders.carry_out(action)

    def spawn(self, job: Coroutine[Any, Any, None], name: str) -> None:
        """Run ``job`` under the server's task group."""
        try:
            assert self._tg is not None
            self._tg.create_task(job, name=name)
        except (AssertionError, RuntimeError):
            # Only after run() was cancelled: a connection aborted then ended late.
            job.close()
            log.warning("server stopped: %s not run", name)

    # -- ticks: one timer, each due room at its own clock reading ---------------------------

    def _arm_ticks(self) -> None:
        """Have the tick timer fire at the earliest due tick (None due: no timer)."""
        due = self.core.next_deadline()
        timer = self._tick_timer
        if timer is not None:
            if due is not None and self._tick_at <= due:
                return  # it fires no later; it re-arms for what is due then
            timer.cancel()
            self._tick_timer = None
        if due is None:
            return
        self._tick_at = due
        delay = max(0.0, due - self.clock())
        self._tick_timer = asyncio.get_running_loop().call_later(delay, self._on_tick)

    def _on_tick(self) -> None:
        """Tick every due room, one at a time, each with a fresh reading of the clock;
        the due subscribers' snapshots are written as each room's actions are applied."""
        self._tick_timer = None
        core, clock = self.core, self.clock
        # At most one pass over the rooms per callback: other callbacks (reads) get the
        # loop between passes even when every room is overdue.
        budget = len(core.rooms) + 1
        now = clock()
        try:
            while budget > 0 and (due := core.next_deadline()) is not None:
                now = clock()
                if due > now + 1e-9:
                    break
                budget -= 1
                core.capacity.tick_lag(now, now - due)
                self.apply(core.tick(now, limit=1))
        finally:
            if now >= self._measure_at:
                self._measure_at = measure(core, self._conns.values(), now)
            self._arm_ticks()
            if self._intake is not None:
                self._intake.accept()

    async def _expiry_loop(self) -> None:
        """Close connections that have not joined in time (``join_timeout``), or whose
        access token expired."""
        changed = self._new_connection
        while True:
            due = self.core.next_expiry()
            now = self.clock()
            if due is None or due > now:
                changed.clear()
                # (asyncio.timeout: wait_for can swallow a cancellation on 3.11)
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(None if due is None else due - now):
                        await changed.wait()
                continue
            self.apply(self.core.expire(now))
            await asyncio.sleep(0)

    # -- rooms and recordings --------------------------------------------------------------

    async def prepare_room(self, name: str) -> None:
        """Make sure room ``name`` exists, opening its recorder off the event loop."""
        if self.config.record_dir is None or name in self.rooms:
            return
        assert self._tg is not None
        await self.recorders.prepare(name, self.rooms, self._tg)

    @property
    def recordings(self) -> list[Path]:
        """Finished recordings, in the order they closed."""
        return self.recorders.paths

    def _socket_gone(self, conn: _Connection) -> None:
        self._sockets.discard(conn)
        if not self._sockets:
            self._all_gone.set()

    # -- lifecycle ---------------------------------------------------------------------

    def pause_recording(self) -> None:
        """Stop recording pose updates in every room, and in rooms opened later.

        Presence, events and drops are still recorded; each file gets one
        ``recording-paused`` drops record (with the updates not recorded) when
        recording resumes or the room closes. ``posecast serve`` does this on
        SIGUSR1 (and resumes on SIGUSR2).
        """
        if self.config.record_dir is None:
            log.warning("pause requested, but this server does not record")
            return
        if not self.core.recording_paused:
            self.apply(self.core.pause_recording(self.clock()))
            log.info("recording paused")

    def resume_recording(self) -> None:
        """Record pose updates again after :meth:`pause_recording`."""
        if self.core.recording_paused:
            self.apply(self.core.resume_recording(self.clock()))
            log.info("recording resumed")

    def stop(self) -> None:
        """Stop accepting, close every connection with 1001 "going away"; run() returns.

        Each close takes at most ``close_timeout`` after the connection's queued
        messages drain (0.5 s at most), even for a peer that stopped reading.
        """
        self._stop.set()

    def _tls_context(self) -> ssl.SSLContext | None:
        """The server TLS context of ``certfile`` / ``keyfile`` (None: plain ws://)."""
        cfg = self.config
        if cfg.certfile is None:
            return None
        ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
        ctx.minimum_version = ssl.TLSVersion.TLSv1_2
        ctx.load_cert_chain(cfg.certfile, cfg.keyfile)
        return ctx

    async def run(self) -> None:
        cfg = self.config
        admission = self.core.admission
        admission.max_total = fd_budget(admission.max_total)
        if cfg.secret is None:
            log.warning("no --secret: the server is open, anyone can join any room")
        if codec.ACCELERATOR_NOTICE:
            log.warning(codec.ACCELERATOR_NOTICE)
        if cfg.record_dir is not None:
            await self.recorders.start()
        if cfg.cluster is not None:
            await self._join_cluster(cfg.cluster)
        try:
            async with asyncio.TaskGroup() as tg:
                self._tg = tg
                expiry = tg.create_task(self._expiry_loop(), name="join-deadlines")
                upkeep = None
                if self.cluster is not None:
                    upkeep = tg.create_task(self.cluster.run(), name="cluster")
                await self._serve()
                expiry.cancel()
                if upkeep is not None:
                    upkeep.cancel()
                if self._tick_timer is not None:
                    self._tick_timer.cancel()
                    self._tick_timer = None
                self.apply(self.core.close_rooms(self.clock()))
        finally:
            # Every room's recording is finished (the task group waited for them);
            # after a failure, rooms still open keep their .part files for recovery.
            await self.recorders.close_hosts()
            if self.cluster is not None:
                await self.cluster.close()

    async def _join_cluster(self, servers: str) -> None:
        """Join the cluster of relays on NATS ``servers`` (ClusterError: one line)."""
        import re
        import socket

        from posecast.server.node import ClusterNode

        cfg = self.config
        self.cluster = await ClusterNode.open(
            servers,
            cfg.node or re.sub(r"[^A-Za-z0-9_-]", "-", socket.gethostname())[:64],
            self.core,
            self.apply,
            self._deliver_forwarded,
            self._close_forwarded,
            url=f"ws://{cfg.host}:{cfg.port}",
            lease=cfg.cluster_lease,
            clock=self.clock,
            wall_clock=self.wall_clock,
            prepare=None if cfg.record_dir is None else self.prepare_room,
        )

    def _deliver_forwarded(self, conn: int, data: bytes) -> None:
        target = self._conns.get(conn)
        if target is not None:
            target.write_forwarded(data)

    def _close_forwarded(self, conn: int, code: int, reason: str) -> None:
        target = self._conns.get(conn)
        if target is not None:
            target.close(code, reason)

    def _recording_metadata(self, room: str) -> dict[str, str] | None:
        return None if self.cluster is None else self.cluster.recording_metadata(room)

    def _cluster_metrics(self) -> str:
        return "" if self.cluster is None else self.cluster.metrics_text()

    async def _serve(self) -> None:
        """Listen until stop(); then close every connection and wait for them to end."""
        cfg = self.config
        loop = asyncio.get_running_loop()
        tls, accept = self._tls_context(), lambda: _Connection(self)
        listener = await loop.create_server(accept, cfg.host, cfg.port, ssl=tls, backlog=ACCEPTS)
        intake = self._intake = Intake(listener, accept, tls, self.spawn)
        try:
            self.port = int(listener.sockets[0].getsockname()[1])
            self.ready.set()
            await self._stop.wait()
            log.info("stopping: closing %d connections", len(self._conns))
            # Every connection closes through its own bounded path (_Connection.close:
            # 0.5 s for the queued messages, then close_timeout for the handshake).
            self._closing = True  # handshakes from now on get a 503
            listener.close()
            intake.close()
            for conn in list(self._conns.values()):
                self.apply(self.core.close(conn.conn, 1001, "going away"))
            for conn in list(self._sockets):
                if not conn.is_open:  # no websocket yet (a handshake, a plain HTTP answer)
                    conn.abort()
            try:  # (bounded: should a socket's end never be reported, it is aborted below)
                await asyncio.wait_for(self._all_gone.wait(), cfg.close_timeout + 5.0)
            except TimeoutError:
                log.warning("stopping: %d connections did not end; aborted", len(self._sockets))
        finally:
            listener.close()
            intake.close()
            for conn in list(self._sockets):
                conn.abort()

    # -- statistics ----------------------------------------------------------------------

    def statistics(self) -> dict[str, object]:
        conns = self.core.connection_statistics()
        return {
            "connections": len(conns),
            "rooms": {name: room.statistics() for name, room in self.rooms.items()},
            "connection_stats": conns,
        }

    def metrics_text(self) -> str:
        """Prometheus text exposition of the server's counters."""
        return metrics_text(self.core, self.clock()) + self._cluster_metrics()


@contextlib.asynccontextmanager
async def serving(server: RelayServer, within: float = 10.0) -> AsyncIterator[RelayServer]:
    """Run ``server`` under a TaskGroup while the block runs: it listens when the block
    starts (``within`` s at most) and has stopped, every connection closed, after."""
    async with asyncio.TaskGroup() as tg:
        tg.create_task(server.run())
        await asyncio.wait_for(server.ready.wait(), within)
        try:
            yield server
        finally:
            server.stop()
