"""The relay's asyncio adapter: sockets, timers and time around :class:`server.core.RelayCore`.

Every rule of the relay lives in the sans-I/O core (``server/core.py``: its
docstring is the protocol); the adapter only carries out what the core decides, with
no task and no Event per connection. It is two modules: this one, the server (the
listening socket, the timers, the actions that are no one connection's, the
lifecycle), and ``server/connection.py``, one websocket as the relay runs it (its
reads fed to the core, its writes, its close). Writes are driven by the core: a
``Wake`` is carried out at once, so after a room tick every due subscriber's
snapshot is written in that same callback.

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
from collections.abc import AsyncIterator, Callable, Coroutine
from pathlib import Path
from typing import TYPE_CHECKING, Any

from posecast.protocol import codec
from posecast.server.connection import Connection, Framer
from posecast.server.core import (
    Action,
    Close,
    ConnectionStatistics,
    FinishRecording,
    Log,
    Rearm,
    RelayCore,
    Reschedule,
    ServerConfig,
    Wake,
)
from posecast.server.handshakes import FD_RESERVE, HEALTH_RESERVE
from posecast.server.http import OriginPolicy, QuietHttpLog, metrics_text, process_request
from posecast.server.intake import Intake, measure
from posecast.server.logs import LogLimiter
from posecast.server.member import IdAllocator
from posecast.server.node import cluster_clock
from posecast.server.recordings import Recordings
from posecast.server.room import Room
from posecast.server.stopping import until_gone, watch_tasks

if TYPE_CHECKING:
    from posecast.server.node import ClusterNode

__all__ = ["ConnectionStatistics", "LogLimiter", "RelayServer", "ServerConfig", "serving"]

log = logging.getLogger("posecast.server")

Clock = Callable[[], float]

#: Listen backlog: connections queued until accepted (past it dropped, to SYN retries).
ACCEPTS = 4096


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
        self._conns: dict[int, Connection] = {}
        #: Connections whose sockets held unsent bytes when last looked at: told to the
        #: core again before each tick (the loop sends between callbacks).
        self.unsent: set[Connection] = set()
        #: Every TCP connection, handshake or not (stop() waits for them all to end).
        self._sockets: set[Connection] = set()
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
        self.frames = Framer()
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
            self._add_room,
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

    def connection_of(self, user: int) -> Connection:
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
            elif isinstance(action, Log):
                log.log(action.level, action.message, *action.args, exc_info=action.error)
            elif isinstance(action, FinishRecording):
                rec = self.recorders.take(action.room)
                if rec is not None:
                    self.spawn(self.recorders.finish(action.room, rec), f"close:{action.room}")
            else:  # Record, RecordPose, PollRecording
                self.recorders.carry_out(action)

    def _add_room(self, name: str, recorded: bool, now: float) -> bool:
        """``RelayCore.add_room``, its log line carried out at once."""
        added = self.core.add_room(name, recorded, now)
        self.apply(self.core.pending())
        return added

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
        for conn in list(self.unsent):  # what the loop sent since: the core reads it
            conn.tell_unsent()
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

    # -- the connections (``server/connection.py``) see the server through these ----------

    def socket_opened(self, conn: Connection) -> None:
        """A TCP connection was accepted (handshake or not): stop() waits for its end."""
        self._sockets.add(conn)
        self._all_gone.clear()

    def socket_gone(self, conn: Connection) -> None:
        """A TCP connection has ended."""
        self._sockets.discard(conn)
        self.unsent.discard(conn)
        if not self._sockets:
            self._all_gone.set()

    def opened(self, conn: Connection, actions: list[Action]) -> None:
        """``conn``'s websocket is open and the core knows it: carry out ``actions`` (a
        refusal over a limit, or a join deadline to watch)."""
        self._conns[conn.conn] = conn
        self.apply(actions)
        self._new_connection.set()

    def serves(self, conn: Connection) -> bool:
        """Whether ``conn`` is still one of the open websockets (it may have ended
        while it waited for a room to open or a cluster claim)."""
        return self._conns.get(conn.conn) is conn

    def ended(self, conn: Connection) -> None:
        """``conn``'s websocket has ended."""
        self._conns.pop(conn.conn, None)

    @property
    def closing(self) -> bool:
        """stop() has begun: handshakes from then on get a 503."""
        return self._closing

    @property
    def stopping(self) -> bool:
        """stop() was called."""
        return self._stop.is_set()

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
        watch = None
        try:
            async with asyncio.TaskGroup() as tg:
                self._tg = tg
                expiry = tg.create_task(self._expiry_loop(), name="join-deadlines")
                upkeep = None
                if self.cluster is not None:
                    upkeep = tg.create_task(self.cluster.run(), name="cluster")
                await self._serve()
                watch = watch_tasks(cfg.close_timeout + 5.0)  # (a stop that hangs says on what)
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
            if watch is not None:
                watch.cancel()

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
        tls, accept = self._tls_context(), lambda: Connection(self)
        listener = await loop.create_server(accept, cfg.host, cfg.port, ssl=tls, backlog=ACCEPTS)
        intake = self._intake = Intake(listener, accept, tls, self.spawn)
        try:
            self.port = int(listener.sockets[0].getsockname()[1])
            self.ready.set()
            await self._stop.wait()
            log.info("stopping: closing %d connections", len(self._conns))
            # Every connection closes through its own bounded path (Connection.close:
            # 0.5 s for the queued messages, then close_timeout for the handshake).
            self._closing = True  # handshakes from now on get a 503
            listener.close()
            intake.close()
            for conn in list(self._conns.values()):
                self.apply(self.core.close(conn.conn, 1001, "going away"))
            for conn in list(self._sockets):
                if not conn.is_open:  # no websocket yet (a handshake, a plain HTTP answer)
                    conn.abort()
            # (bounded: a socket whose end is not reported is named, then aborted below)
            await until_gone(self._sockets, self._all_gone, cfg.close_timeout + 5.0)
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


def fd_budget(max_connections: int) -> int:
    """The most connections this process can hold with ``FD_RESERVE`` + ``HEALTH_RESERVE``
    descriptors to spare (its ``nofile`` soft limit raised to the hard one first);
    ``max_connections`` if that fits, or if the limit cannot be read (not POSIX)."""
    try:
        import resource
    except ImportError:  # pragma: no cover - Windows
        return max_connections
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard == resource.RLIM_INFINITY or hard > soft:
        target = 1 << 20 if hard == resource.RLIM_INFINITY else hard
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
            soft = target
        except (ValueError, OSError):
            pass
    budget = max(1, soft - FD_RESERVE - HEALTH_RESERVE)
    if max_connections == 0 or max_connections > budget:
        log.warning(
            "nofile limit %d: at most %d connections (not %s), so that /healthz, "
            "/metrics and the recordings always have descriptors",
            soft, budget, max_connections or "unlimited",
        )  # fmt: skip
        return budget
    return max_connections


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
