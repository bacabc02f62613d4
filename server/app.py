"""The relay's asyncio adapter: sockets, tasks and time around :class:`server.core.RelayCore`.

Every rule of the relay lives in the sans-I/O core (``server/core.py``: its
docstring is the protocol); this module only carries out what the core
decides. Each websocket runs three tasks under one ``TaskGroup``: a reader
that feeds received frames to the core, a writer that writes what
:meth:`RelayCore.take` hands out when the core wakes it (``Wake``), and a
closer that closes the socket when the core says so (``Close``), after the
queued messages are written. One tick loop, under the server's own
``TaskGroup``, sleeps until :meth:`RelayCore.next_deadline` and ticks the
rooms; another sleeps until :meth:`RelayCore.next_expiry` and closes the
connections that have not joined in time. Recordings open and close off the
event loop. ``GET /healthz`` and ``GET /metrics`` are answered on the websocket
port (``server/http.py``).

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
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.exceptions import ConnectionClosed
from websockets.protocol import State as WsState

from protocol import UserEvent
from server.core import (
    Action,
    Close,
    ConnectionStatistics,
    FinishRecording,
    Rearm,
    RelayCore,
    Reschedule,
    ServerConfig,
    Wake,
)
from server.http import QuietHttpLog, metrics_text, process_request
from server.logs import LogLimiter
from server.room import IdAllocator, Outbox, Room

if TYPE_CHECKING:
    from recorder import RecorderHost, RecordOptions, RoomRecorder

__all__ = ["ConnectionStatistics", "LogLimiter", "RelayServer", "ServerConfig"]

log = logging.getLogger("posecast.server")

Clock = Callable[[], float]


class _Connection:
    """One websocket and the events its tasks wait on."""

    def __init__(self, server: RelayServer, ws: ServerConnection) -> None:
        self.server = server
        self.ws = ws
        address = ws.remote_address[0] if ws.remote_address else None
        self.conn = server.core.connect(server.clock(), self._buffered, address)
        self.peer = server.core.peer(self.conn)
        self.wake = asyncio.Event()
        #: Set while no reliable message waits to be written.
        self.idle = asyncio.Event()
        self.idle.set()
        self.must_close = asyncio.Event()
        self.close_request: tuple[int, str] | None = None

    @property
    def outbox(self) -> Outbox:
        return self.peer.outbox

    @property
    def user(self) -> int | None:
        return self.peer.user

    def _buffered(self) -> int:
        transport = self.ws.transport
        return 0 if transport is None else int(transport.get_write_buffer_size())

    def statistics(self) -> ConnectionStatistics:
        return self.peer.statistics()

    async def read_loop(self) -> None:
        server, core, conn = self.server, self.server.core, self.conn
        count = 0
        try:
            async for data in self.ws:
                relayed = False
                for event in core.frame(conn, data):
                    room = core.room_to_open(conn, event, server.wall_clock())
                    if room is not None:
                        # A new room's recorder opens off the event loop first.
                        await server.prepare_room(room)
                    server.apply(core.handle(conn, event, server.clock(), server.wall_clock()))
                    relayed = relayed or isinstance(event, UserEvent)
                count += 1
                # A peer flooding us must not starve the other connections. After
                # a relayed event, let the peers' writers drain it before the next
                # one: their bounded queues must measure how slow *they* are, not
                # how many events this reader handled in one go.
                if relayed or count % 32 == 0:
                    await asyncio.sleep(0)
        except ConnectionClosed:
            pass

    async def write_loop(self) -> None:
        server, core, clock = self.server, self.server.core, self.server.clock
        next_at: float | None = None
        try:
            while True:
                # asyncio.timeout, not wait_for: on 3.11 wait_for can swallow a
                # cancellation that arrives as the wake-up does, and loop forever.
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(None if next_at is None else next_at - clock()):
                        await self.wake.wait()
                self.wake.clear()
                frames, next_at = core.take(self.conn, clock())
                # The link's rate adaptation may have moved a tick earlier: the tick
                # loop must hear it now, not at the next action some reader causes.
                server.apply(core.pending())
                for data in frames:
                    await self.ws.send(data)
                if not core.events_pending(self.conn):
                    self.idle.set()
        except ConnectionClosed:
            pass

    def wake_up(self) -> None:
        if self.server.core.events_pending(self.conn):
            self.idle.clear()
        self.wake.set()

    def close(self, code: int, reason: str) -> None:
        if self.close_request is None:
            self.close_request = (code, reason)
            self.must_close.set()

    async def close_watch(self) -> None:
        await self.must_close.wait()
        assert self.close_request is not None
        code, reason = self.close_request
        # Let queued messages (the error that explains the close) go out first.
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(0.5):
                await self.idle.wait()
        await self.close_now(code, reason)

    async def close_now(self, code: int, reason: str) -> None:
        """Closing handshake, bounded by ``close_timeout``; then drop the TCP connection.

        ``ws.close`` waits for the write buffer to drain before it waits (with a
        timeout) for the peer's close frame, and a peer that never reads never
        lets it drain: without this bound its connection would never end.
        """
        try:
            async with asyncio.timeout(self.server.config.close_timeout):
                await self.ws.close(code, reason)
        except TimeoutError:
            log.info("user %s: no closing handshake, dropping the connection", self.user)
            self.ws.transport.abort()


class RelayServer:
    """The relay: ``await RelayServer(config).run()`` serves until :meth:`stop`."""

    def __init__(
        self,
        config: ServerConfig | None = None,
        clock: Clock = time.monotonic,
        wall_clock: Clock = time.time,
    ) -> None:
        self.config = config or ServerConfig()
        self.clock = clock
        self.wall_clock = wall_clock
        self.core = RelayCore(self.config)
        self.limits = self.core.limits
        self._conns: dict[int, _Connection] = {}
        self._tg: asyncio.TaskGroup | None = None
        self._opening: dict[str, asyncio.Task[None]] = {}
        self._reschedule = asyncio.Event()
        #: Set when a connection opens: its join deadline may be the next expiry.
        self._new_connection = asyncio.Event()
        # The one writer process every recorded room shares (started with the
        # server, again for the next room after a crash of the previous one).
        self._recorder_host: RecorderHost | None = None
        self._host_lock = threading.Lock()
        self._retired_hosts: list[RecorderHost] = []
        #: Finished recordings, in the order they closed.
        self.recordings: list[Path] = []
        self._stop = asyncio.Event()
        self._ws_server: Server | None = None
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

    @property
    def recording_paused(self) -> bool:
        return self.core.recording_paused

    def connection_of(self, user: int) -> _Connection:
        return self._conns[self.core.peer_of(user).conn]

    # -- carrying out the core's decisions ------------------------------------------------

    def apply(self, actions: list[Action]) -> None:
        for action in actions:
            if isinstance(action, Wake):
                conn = self._conns.get(action.conn)
                if conn is not None:
                    conn.wake_up()
            elif isinstance(action, Close):
                conn = self._conns.get(action.conn)
                if conn is not None:
                    conn.close(action.code, action.reason)
            elif isinstance(action, Reschedule):
                self._reschedule.set()
            elif isinstance(action, Rearm):
                self._new_connection.set()
            elif isinstance(action, FinishRecording):
                assert self._tg is not None
                self._tg.create_task(
                    self._close_recorder(action.room, action.recorder),
                    name=f"close:{action.room}",
                )

    async def _tick_loop(self) -> None:
        """Tick the rooms at every due time; sleep until the next one or a change."""
        await self._deadline_loop(self.core.next_deadline, self.core.tick, self._reschedule)

    async def _expiry_loop(self) -> None:
        """Close connections that have not joined in time (``join_timeout``), or whose
        access token expired."""
        await self._deadline_loop(self.core.next_expiry, self.core.expire, self._new_connection)

    async def _deadline_loop(
        self,
        next_due: Callable[[], float | None],
        run: Callable[[float], list[Action]],
        changed: asyncio.Event,
    ) -> None:
        """Call ``run(now)`` at every time ``next_due()`` names; ``changed`` wakes early."""
        while True:
            due = next_due()
            now = self.clock()
            if due is None or due > now:
                changed.clear()
                # (asyncio.timeout: wait_for can swallow a cancellation on 3.11)
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(None if due is None else due - now):
                        await changed.wait()
                continue
            self.apply(run(now))
            await asyncio.sleep(0)

    # -- rooms and recordings --------------------------------------------------------------

    async def prepare_room(self, name: str) -> None:
        """Make sure room ``name`` exists, opening its recorder off the event loop."""
        if self.config.record_dir is None or name in self.rooms:
            return
        pending = self._opening.get(name)
        if pending is None:
            assert self._tg is not None
            pending = self._tg.create_task(self._open_room(name), name=f"open:{name}")
            self._opening[name] = pending
        await asyncio.shield(pending)

    async def _open_room(self, name: str) -> None:
        from recorder import RecordOptions, SessionRecorder

        directory = self.config.record_dir
        assert directory is not None
        opener: Callable[..., RoomRecorder] = (
            SessionRecorder.open if self.config.record_writer == "thread" else self._open_on_host
        )
        try:
            options = RecordOptions(
                clock=self.clock,
                wall_clock=self.wall_clock,
                # A hand-off (one pipe write, one wake-up of the writer) at most
                # every 0.25 s: records reach the disk within 0.25 + 0.05 + 0.5 s.
                batch_size=1024,
                batch_delay=0.25,
            )
            rec: RoomRecorder | None = await asyncio.to_thread(opener, directory, name, options)
        except Exception:
            log.exception("cannot record room %r; it runs unrecorded", name)
            rec = None
        try:
            if self.core.add_room(name, rec, self.clock()):
                if rec is not None:
                    log.info("recording room %r to %s", name, rec.path)
            elif rec is not None:
                await rec.aclose()
        finally:
            self._opening.pop(name, None)

    def _open_on_host(self, directory: Path, name: str, options: RecordOptions) -> RoomRecorder:
        """Open room ``name``'s recording on the shared writer process (a worker thread)."""
        return self._ensure_host().open_room(directory, name, options)

    def _ensure_host(self) -> RecorderHost:
        """The running writer process; a new one if there is none or it died (blocks)."""
        from recorder import RecorderHost

        with self._host_lock:
            host = self._recorder_host
            if host is None or not host.alive:
                if host is not None:
                    log.warning("the recorder process is gone; starting a new one")
                    self._retired_hosts.append(host)
                host = self._recorder_host = RecorderHost.start()
                log.info("recorder process started (pid %d)", host.pid)
            return host

    async def _close_hosts(self) -> None:
        """Wait for the writer process(es) to end, once every room is closed."""
        hosts = [*self._retired_hosts, self._recorder_host]
        self._recorder_host, self._retired_hosts = None, []
        for host in hosts:
            if host is not None:
                code = await asyncio.to_thread(host.close)
                if code != 0:
                    log.warning("the recorder process exited with code %s", code)

    async def _close_recorder(self, name: str, rec: RoomRecorder) -> None:
        try:
            path = await rec.aclose(self.clock())
            self.recordings.append(path)
            log.info("room %r recorded to %s", name, path)
        except Exception:
            log.exception("recording of room %r did not finish cleanly", name)

    async def _handler(self, ws: ServerConnection) -> None:
        conn = _Connection(self, ws)
        self._conns[conn.conn] = conn
        # Refused over a connection limit (a Close), or a join deadline to watch.
        self.apply(self.core.pending())
        self._new_connection.set()
        if self._stop.is_set():
            # Its handshake finished after stop() had closed the others. Through the
            # core, which then handles nothing more it sends (no hello, no join).
            self.apply(self.core.close(conn.conn, 1001, "going away"))
        try:
            async with asyncio.TaskGroup() as tg:
                writer = tg.create_task(conn.write_loop())
                closer = tg.create_task(conn.close_watch())
                await conn.read_loop()
                writer.cancel()
                closer.cancel()
        finally:
            self._conns.pop(conn.conn, None)
            # A close frame from the client is a goodbye; a dropped socket may resume.
            said_bye = getattr(ws.protocol, "close_rcvd", None) is not None
            self.apply(self.core.disconnect(conn.conn, self.clock(), said_bye))
            if ws.state is WsState.OPEN:
                # Only after a bug (the reader ended without the socket closing):
                # websockets would close without a bound, so close here.
                await conn.close_now(1011, "internal-error")

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
            self.core.pause_recording(self.clock())
            log.info("recording paused")

    def resume_recording(self) -> None:
        """Record pose updates again after :meth:`pause_recording`."""
        if self.core.recording_paused:
            self.core.resume_recording(self.clock())
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
        if cfg.secret is None:
            log.warning("no --secret: the server is open, anyone can join any room")
        if cfg.record_dir is not None:
            from recorder import recover_leftovers

            cfg.record_dir.mkdir(parents=True, exist_ok=True)
            for report in await asyncio.to_thread(recover_leftovers, cfg.record_dir):
                log.warning("recovered leftover recording: %s", report.summary())
            if cfg.record_writer == "process":
                # Up front, so that no join waits for the writer's start-up.
                try:
                    await asyncio.to_thread(self._ensure_host)
                except Exception:
                    log.exception("cannot start the recorder process; each new room will retry")
        try:
            async with asyncio.TaskGroup() as tg:
                self._tg = tg
                ticker = tg.create_task(self._tick_loop(), name="ticks")
                expiry = tg.create_task(self._expiry_loop(), name="join-deadlines")
                async with serve(
                    self._handler,
                    cfg.host,
                    cfg.port,
                    process_request=process_request(self.core, self.clock),
                    logger=QuietHttpLog(logging.getLogger("websockets.server"), {}),
                    max_size=self.limits.max_frame_size,
                    close_timeout=cfg.close_timeout,
                    compression=None,
                    ssl=self._tls_context(),
                    ping_interval=cfg.ping_interval or None,
                    ping_timeout=cfg.ping_timeout or None,
                ) as ws_server:
                    self._ws_server = ws_server
                    sock = next(iter(ws_server.sockets))
                    self.port = int(sock.getsockname()[1])
                    self.ready.set()
                    await self._stop.wait()
                    log.info("stopping: closing %d connections", len(self._conns))
                    # Every connection closes through its own bounded path (see
                    # _Connection.close_now); websockets' own close could wait forever
                    # on a peer that does not read. Handshakes from now on get a 503.
                    ws_server.close(close_connections=False)
                    for conn in list(self._conns.values()):
                        self.apply(self.core.close(conn.conn, 1001, "going away"))
                    await ws_server.wait_closed()
                ticker.cancel()
                expiry.cancel()
                self.apply(self.core.close_rooms(self.clock()))
        finally:
            # Every room's recording is finished (the task group waited for them);
            # after a failure, rooms still open keep their .part files for recovery.
            await self._close_hosts()

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
        return metrics_text(self.core, self.clock())
