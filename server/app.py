"""The asyncio relay: websocket connections, rooms, HTTP health and metrics.

Each connection runs three tasks under one ``TaskGroup``: a reader feeding the
sans-I/O :class:`protocol.ServerSession`, a writer draining the connection's
:class:`server.room.Outbox` (events in order, then the newest snapshot), and a
closer that waits for a decision to close. Room tick loops run under the
server's own ``TaskGroup``. ``GET /healthz`` and ``GET /metrics`` (Prometheus
text) are served on the websocket port.
"""

from __future__ import annotations

import asyncio
import contextlib
import heapq
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from http import HTTPStatus
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response
from websockets.protocol import State as WsState

from protocol import (
    Bye,
    ErrorCode,
    ErrorMessage,
    Hello,
    Join,
    Joined,
    Limits,
    LocalProtocolError,
    PeerJoined,
    PeerLeft,
    Ping,
    Pong,
    PoseUpdate,
    ProtocolError,
    ServerSession,
    SetRate,
    UserEvent,
    close_reason,
)
from protocol.events import Event, Message
from scenarios.network import EgressLink, Tier
from server.auth import TokenError, verify_token
from server.room import DEFAULT_EVENT_QUEUE, IdAllocator, Member, Outbox, Room, room_phase

if TYPE_CHECKING:
    from recorder import RecorderHost, RoomRecorder

__all__ = ["ConnectionStatistics", "RelayServer", "ServerConfig"]

# Websocket framing of a server frame of 126-65535 bytes (no mask): what the
# emulated link charges on top of the frame itself.
_WS_HEADER = 4

log = logging.getLogger("posecast.server")

Clock = Callable[[], float]


@dataclass(frozen=True)
class ServerConfig:
    """Everything ``posecast serve`` can set."""

    host: str = "127.0.0.1"
    port: int = 8765
    rate: float = 20.0
    min_rate: float = 5.0
    max_rate: float = 30.0
    secret: str | None = None
    max_event_queue: int = DEFAULT_EVENT_QUEUE
    #: A subscriber with more than this many bytes unsent gets no new snapshot.
    congested_bytes: int = 64 * 1024
    #: Pose updates per second one connection may publish (bucket of one second).
    max_update_rate: float = 120.0
    close_timeout: float = 2.0
    #: Record every room session into this folder (``posecast serve --record``).
    record_dir: Path | None = None
    #: Where the recorder's MCAP writer runs: ``process`` (a child process fed the
    #: raw update frames through a pipe; the relay's own cost per update is two
    #: list appends) or ``thread`` (a thread of the server's process).
    record_writer: Literal["process", "thread"] = "process"
    #: Emulate this network tier on every subscriber's downlink (``--link``).
    link: Tier | None = None
    #: Snapshots held in one subscriber's emulated link at most (older ones drop).
    link_max_in_flight: int = 64


#: ConnectionStatistics fields that only ever grow, summed over ended connections.
_COUNTERS = (
    "frames_in",
    "bytes_in",
    "frames_out",
    "bytes_out",
    "snapshots_offered",
    "skips",
    "congestion_skips",
    "event_drops",
    "flood_drops",
    "protocol_errors",
)


@dataclass(frozen=True, slots=True)
class ConnectionStatistics:
    user: int | None
    room: str | None
    frames_in: int
    bytes_in: int
    frames_out: int
    bytes_out: int
    snapshots_offered: int
    skips: int
    congestion_skips: int
    event_drops: int
    flood_drops: int
    protocol_errors: int
    #: With an emulated link: the rate the server chose for this subscriber (Hz),
    #: snapshots delivered / skipped at the cap / lost, and bytes on the link.
    link_rate_hz: float | None = None
    link_frames: int = 0
    link_cap_skips: int = 0
    link_lost: int = 0
    link_bytes: int = 0


class _Connection:
    """One websocket: session state, outbox and counters."""

    def __init__(self, server: RelayServer, ws: ServerConnection) -> None:
        self.server = server
        self.ws = ws
        cfg = server.config
        self.session = ServerSession(server.limits)
        self.outbox = Outbox(cfg.max_event_queue, self._buffered, cfg.congested_bytes)
        self.user: int | None = None
        self.name = ""
        self.room: Room | None = None
        self.member: Member | None = None
        self.close_request: tuple[int, str] | None = None
        self.must_close = asyncio.Event()
        self.frames_in = self.bytes_in = self.frames_out = self.bytes_out = 0
        self.event_drops = self.flood_drops = self.protocol_errors = 0
        #: The emulated downlink (``ServerConfig.link``), set at join.
        self.link: EgressLink | None = None
        self._delayed: list[tuple[float, int, bytes]] = []
        self._link_seq = 0
        self.link_overflow = 0
        self._bucket = cfg.max_update_rate
        self._bucket_time = server.clock()

    def _buffered(self) -> int:
        transport = self.ws.transport
        return 0 if transport is None else int(transport.get_write_buffer_size())

    # -- sending -------------------------------------------------------------------

    def send(self, message: Message) -> None:
        """Queue a reliable message; overflow closes this connection, not others.

        Called from other connections' readers (peer notices, relayed events), so
        it never raises: a message this session may no longer carry (it ended on
        a fatal error or bye) is dropped.
        """
        if self.close_request is not None:
            return
        try:
            data = self.session.send(message)
        except LocalProtocolError as exc:
            log.info("user %s: not sent (%s)", self.user, exc)
            return
        if not self.outbox.offer_event(data):
            self.event_drops += 1
            self.close(
                ErrorCode.TOO_SLOW.close_code or 1008,
                f"too-slow: event queue overflow ({self.outbox.max_events})",
            )

    def close(self, code: int, reason: str) -> None:
        """Ask the closer task to close the websocket (first request wins)."""
        if self.close_request is None:
            self.close_request = (code, close_reason(reason))
            self.must_close.set()

    # -- tasks ---------------------------------------------------------------------

    async def read_loop(self) -> None:
        count = 0
        try:
            async for data in self.ws:
                self.frames_in += 1
                relayed = False
                if self.close_request is not None:
                    # Closing: what it still sends cannot matter to anyone.
                    self.bytes_in += len(data)
                elif isinstance(data, str):
                    self.bytes_in += len(data.encode())
                    self._protocol_error(
                        ProtocolError(ErrorCode.BAD_FRAME, "text frames are not allowed")
                    )
                else:
                    self.bytes_in += len(data)
                    now = self.server.clock()
                    for event in self.session.receive_data(data):
                        if (
                            isinstance(event, Join)
                            and self.server.config.record_dir is not None
                            and self._join_permitted(event)
                        ):
                            # A new room's recorder opens off the event loop first.
                            await self.server.prepare_room(event.room)
                            now = self.server.clock()
                        self._handle(event, now)
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
        outbox = self.outbox
        clock = self.server.clock
        delayed = self._delayed
        try:
            while True:
                if delayed:
                    with contextlib.suppress(TimeoutError):
                        await asyncio.wait_for(
                            outbox.wake.wait(), max(0.0, delayed[0][0] - clock())
                        )
                else:
                    await outbox.wake.wait()
                outbox.wake.clear()
                now = clock()
                while delayed and delayed[0][0] <= now:
                    await self._write(heapq.heappop(delayed)[2])
                while True:
                    data, is_snapshot = outbox.take_with_kind()
                    if data is None:
                        break
                    if is_snapshot and self.link is not None:
                        self._into_link(data, now)
                    else:
                        await self._write(data)
                outbox.idle.set()
        except ConnectionClosed:
            pass

    async def _write(self, data: bytes) -> None:
        await self.ws.send(data)
        self.frames_out += 1
        self.bytes_out += len(data)

    def _into_link(self, data: bytes, now: float) -> None:
        """Put a snapshot on the emulated link; adopt the rate its cap allows."""
        link = self.link
        assert link is not None
        arrival = link.offer(now, len(data) + _WS_HEADER)
        if arrival is not None:
            if len(self._delayed) >= self.server.config.link_max_in_flight:
                heapq.heappop(self._delayed)
                self.link_overflow += 1
            self._link_seq += 1
            heapq.heappush(self._delayed, (arrival, self._link_seq, data))
        room, member = self.room, self.member
        if room is not None and member is not None:
            rate = max(self.server.config.min_rate, link.rate_for(member.asked_rate))
            if abs(rate - member.rate) > 0.25:
                room.set_rate(member.user, rate, now)

    async def close_watch(self) -> None:
        await self.must_close.wait()
        assert self.close_request is not None
        code, reason = self.close_request
        # Let queued messages (the error that explains the close) go out first.
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(0.5):
                await self.outbox.idle.wait()
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

    # -- events --------------------------------------------------------------------

    def _protocol_error(self, err: ProtocolError) -> None:
        self.protocol_errors += 1
        log.info("user %s: %s (%s)", self.user, err.message, err.code)
        self.send(err.to_message())
        if err.fatal:
            self.close(err.close_code or 1002, err.close_reason)

    def _handle(self, event: Event, now: float) -> None:
        if isinstance(event, PoseUpdate):
            self._on_update(event, now)
        elif isinstance(event, Ping):
            self.send(
                Pong(
                    seq=event.seq,
                    ping_time=event.time,
                    recv_time=now,
                    send_time=self.server.clock(),
                )
            )
        elif isinstance(event, ProtocolError):
            self._protocol_error(event)
        elif isinstance(event, Hello):
            self.user = self.server.users.take()
            self.server.register(self)
            self.name = event.agent or f"user{self.user}"
            self.send(self.session.make_welcome(self.user, now))
        elif isinstance(event, Join):
            self._on_join(event, now)
        elif isinstance(event, SetRate):
            if self.room is not None and self.user is not None:
                if self.member is not None:
                    self.member.asked_rate = event.rate
                rate = event.rate if self.link is None else self.link.rate_for(event.rate)
                self.room.set_rate(self.user, max(self.server.config.min_rate, rate), now)
                if self.room.recorder is not None:
                    self.room.recorder.record_presence(
                        {"kind": "rate", "user": self.user, "rate": event.rate}, now
                    )
        elif isinstance(event, UserEvent):
            if self.room is not None and self._admit(now):
                for m in list(self.room.members.values()):
                    if m.user != self.user:
                        self.server.connection_of(m.user).send(event)
                if self.room.recorder is not None:
                    self.room.recorder.record_event(
                        {
                            "kind": event.kind,
                            "user": event.user,
                            "stream": event.stream,
                            "time": event.time,
                            "payload": event.payload,
                        },
                        now,
                    )
        elif isinstance(event, Bye):
            self.close(1000, event.reason or "bye")
        elif isinstance(event, ErrorMessage):
            log.info("user %s reports %s: %s", self.user, event.code, event.message)
            if event.fatal:
                # Its session is over (CLOSED): nothing more may be sent to it.
                self.close(1000, f"client ended the session: {event.code}")

    def _join_permitted(self, join: Join) -> bool:
        secret = self.server.config.secret
        if secret is None:
            return True
        try:
            verify_token(secret, join.token, join.room, self.server.wall_clock())
        except TokenError:
            return False
        return True

    def _on_join(self, join: Join, now: float) -> None:
        server = self.server
        if server.config.secret is not None:
            try:
                claims = verify_token(
                    server.config.secret, join.token, join.room, server.wall_clock()
                )
            except TokenError as exc:
                self.send(
                    ErrorMessage.from_code(ErrorCode.UNAUTHORIZED, str(exc), in_reply_to="join")
                )
                self.close(1008, str(exc))
                return
            self.name = claims.user
        assert self.user is not None  # the state table puts hello before join
        room = server.room_for(join.room)
        streams = room.allocate_streams(join.streams)
        self.send(Joined(room=join.room, streams=streams, rate=join.rate))
        member = Member(
            self.user,
            self.name,
            streams,
            join.rate,
            self.outbox,
            label=join.label,
            velocities=join.wants_velocities,
            sends_velocities=join.sends_velocities,
        )
        member.asked_rate = join.rate
        if server.config.link is not None:
            self.link = EgressLink(server.config.link, seed=self.user)
        for other in room.members.values():
            self.send(
                PeerJoined(
                    user=other.user,
                    streams=other.streams,
                    label=other.label,
                    velocities=other.sends_velocities,
                )
            )
            server.connection_of(other.user).send(
                PeerJoined(
                    user=self.user,
                    streams=streams,
                    label=join.label,
                    velocities=join.sends_velocities,
                )
            )
        room.add(member, now)
        self.room, self.member = room, member
        if room.recorder is not None:
            room.recorder.record_presence(
                {
                    "kind": "join",
                    "user": self.user,
                    "name": self.name,
                    "label": join.label,
                    "streams": streams,
                    "rate": join.rate,
                },
                now,
            )

    def _admit(self, now: float) -> bool:
        """Token bucket over pose updates and events: ``max_update_rate`` a second.

        Holds one second's worth, so bursts are fine; what exceeds it is dropped
        and counted, and a connection that keeps flooding is closed.
        """
        rate = self.server.config.max_update_rate
        self._bucket = min(rate, self._bucket + (now - self._bucket_time) * rate)
        self._bucket_time = now
        if self._bucket < 1.0:
            self.flood_drops += 1
            if self.room is not None and self.user is not None:
                self.room.note_drop("flood", self.user)
            if self.flood_drops > 10 * rate:
                self.close(1008, f"update flood: over {rate:g} updates/s")
            return False
        self._bucket -= 1.0
        return True

    def _on_update(self, update: PoseUpdate, now: float) -> None:
        room, user = self.room, self.user
        if self._admit(now) and room is not None and user is not None:
            stale = room.ingest(user, update)
            rec = room.recorder
            if rec is not None:
                if room.recording_paused:
                    room.paused_updates += 1
                    return
                rec.record_pose_update(user, now, update)
                if stale:
                    room.note_drop("stale", user, stale)

    def leave(self) -> None:
        room, user = self.room, self.user
        if room is not None and user is not None:
            room.remove(user)
            if room.recorder is not None:
                room.recorder.record_presence(
                    {"kind": "leave", "user": user, "reason": "left"}, self.server.clock()
                )
            for other in list(room.members.values()):
                self.server.connection_of(other.user).send(PeerLeft(user=user, reason="left"))
            self.server.forget_room_if_empty(room)
        self.room = self.member = None

    def statistics(self) -> ConnectionStatistics:
        m = self.member
        return ConnectionStatistics(
            user=self.user,
            room=self.room.name if self.room else None,
            frames_in=self.frames_in,
            bytes_in=self.bytes_in,
            frames_out=self.frames_out,
            bytes_out=self.bytes_out,
            snapshots_offered=self.outbox.snapshots_offered,
            skips=self.outbox.skips,
            congestion_skips=m.congestion_skips if m else 0,
            event_drops=self.event_drops,
            flood_drops=self.flood_drops,
            protocol_errors=self.protocol_errors,
            link_rate_hz=m.rate if (m is not None and self.link is not None) else None,
            link_frames=self.link.frames if self.link else 0,
            link_cap_skips=self.link.cap_skips if self.link else 0,
            link_lost=self.link.lost if self.link else 0,
            link_bytes=self.link.bytes if self.link else 0,
        )


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
        self.limits = Limits(min_rate=self.config.min_rate, max_rate=self.config.max_rate)
        self.users = IdAllocator()
        self.rooms: dict[str, Room] = {}
        self._connections: dict[int, _Connection] = {}
        self._all: set[_Connection] = set()
        self._tg: asyncio.TaskGroup | None = None
        self._opening: dict[str, asyncio.Task[None]] = {}
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
        self.closed_connections = 0
        #: Pose updates are not recorded while set (see :meth:`pause_recording`).
        self.recording_paused = False
        #: Counters of connections that have ended (live ones are added on demand),
        #: so that the Prometheus counters never go down.
        self.totals = dict.fromkeys(_COUNTERS, 0)

    # -- rooms and connections -------------------------------------------------------

    def room_for(self, name: str) -> Room:
        room = self.rooms.get(name)
        if room is None:
            room = self.rooms[name] = Room(name, phase=room_phase(name))
            assert self._tg is not None
            self._tg.create_task(self._run_room(room), name=f"room:{name}")
            log.info("room %r created", name)
        return room

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
        from recorder import SessionRecorder

        directory = self.config.record_dir
        assert directory is not None
        opener: Callable[..., RoomRecorder] = (
            SessionRecorder.open if self.config.record_writer == "thread" else self._open_on_host
        )
        try:
            rec: RoomRecorder | None = await asyncio.to_thread(
                opener,
                directory,
                name,
                clock=self.clock,
                wall_clock=self.wall_clock,
                # A hand-off (one pipe write, one wake-up of the writer) at most
                # every 0.25 s: records reach the disk within 0.25 + 0.05 + 0.5 s.
                batch_size=1024,
                batch_delay=0.25,
            )
        except Exception:
            log.exception("cannot record room %r; it runs unrecorded", name)
            rec = None
        try:
            if name not in self.rooms:
                room = self.room_for(name)
                room.recorder = rec
                if rec is not None:
                    log.info("recording room %r to %s", name, rec.path)
                    if self.recording_paused:
                        room.pause_recording(self.clock())
            elif rec is not None:
                await rec.aclose()
        finally:
            self._opening.pop(name, None)

    def _open_on_host(self, directory: Path, name: str, **options: Any) -> RoomRecorder:
        """Open room ``name``'s recording on the shared writer process (a worker thread)."""
        return self._ensure_host().open_room(directory, name, **options)

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

    async def _close_recorder(self, room: Room) -> None:
        rec = room.recorder
        if rec is None:
            return
        now = self.clock()
        room.resume_recording(now)  # a pause in progress goes into the file
        room.flush_drops(now, force=True)  # the drops of the last second too
        room.recorder = None
        try:
            path = await rec.aclose(self.clock())
            self.recordings.append(path)
            log.info("room %r recorded to %s", room.name, path)
        except Exception:
            log.exception("recording of room %r did not finish cleanly", room.name)

    async def _run_room(self, room: Room) -> None:
        """A room's tick loop; a bug in it ends that room's connections, not the server."""
        try:
            await room.run(self.clock)
        except Exception:
            log.exception("room %r failed", room.name)
            if self.rooms.get(room.name) is room:
                del self.rooms[room.name]
            for member in list(room.members.values()):
                conn = self._connections.get(member.user)
                if conn is not None:
                    conn.close(1011, "internal-error: room failed")

    def forget_room_if_empty(self, room: Room) -> None:
        if not room.members and self.rooms.get(room.name) is room:
            del self.rooms[room.name]
            room.retire()
            log.info("room %r removed", room.name)
            if room.recorder is not None and self._tg is not None:
                self._tg.create_task(self._close_recorder(room), name=f"close:{room.name}")

    def register(self, conn: _Connection) -> None:
        assert conn.user is not None
        self._connections[conn.user] = conn

    def connection_of(self, user: int) -> _Connection:
        return self._connections[user]

    async def _handler(self, ws: ServerConnection) -> None:
        conn = _Connection(self, ws)
        self._all.add(conn)
        if self._stop.is_set():
            # Its handshake finished after stop() had closed the others.
            conn.close(1001, "going away")
        try:
            async with asyncio.TaskGroup() as tg:
                writer = tg.create_task(conn.write_loop())
                closer = tg.create_task(conn.close_watch())
                await conn.read_loop()
                writer.cancel()
                closer.cancel()
        finally:
            stats = conn.statistics()  # before leave(): it forgets the member's counters
            conn.leave()
            if conn.user is not None:
                self._connections.pop(conn.user, None)
                self.users.give_back(conn.user)
            self._all.discard(conn)
            self.closed_connections += 1
            for key in _COUNTERS:
                self.totals[key] += getattr(stats, key)
            if ws.state is WsState.OPEN:
                # Only after a bug (the reader ended without the socket closing):
                # websockets would close without a bound, so close here.
                await conn.close_now(1011, "internal-error")

    # -- HTTP ------------------------------------------------------------------------

    def _process_request(self, connection: ServerConnection, request: Request) -> Response | None:
        path = request.path.split("?", 1)[0]
        if path == "/healthz":
            return connection.respond(HTTPStatus.OK, "ok\n")
        if path == "/metrics":
            response = connection.respond(HTTPStatus.OK, self.metrics_text())
            # Same headers as /healthz (Date, Connection: close), Prometheus' type.
            del response.headers["Content-Type"]
            response.headers["Content-Type"] = "text/plain; version=0.0.4; charset=utf-8"
            return response
        return None

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
        if not self.recording_paused:
            self.recording_paused = True
            now = self.clock()
            for room in self.rooms.values():
                room.pause_recording(now)
            log.info("recording paused")

    def resume_recording(self) -> None:
        """Record pose updates again after :meth:`pause_recording`."""
        if self.recording_paused:
            self.recording_paused = False
            now = self.clock()
            for room in self.rooms.values():
                room.resume_recording(now)
            log.info("recording resumed")

    def stop(self) -> None:
        """Stop accepting, close every connection with 1001 "going away"; run() returns.

        Each close takes at most ``close_timeout`` after the connection's queued
        messages drain (0.5 s at most), even for a peer that stopped reading.
        """
        self._stop.set()

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
                async with serve(
                    self._handler,
                    cfg.host,
                    cfg.port,
                    process_request=self._process_request,
                    max_size=self.limits.max_frame_size,
                    close_timeout=cfg.close_timeout,
                    compression=None,
                ) as ws_server:
                    self._ws_server = ws_server
                    sock = next(iter(ws_server.sockets))
                    self.port = int(sock.getsockname()[1])
                    self.ready.set()
                    await self._stop.wait()
                    log.info("stopping: closing %d connections", len(self._all))
                    # Every connection closes through its own bounded path (see
                    # _Connection.close_now); websockets' own close could wait forever
                    # on a peer that does not read. Handshakes from now on get a 503.
                    ws_server.close(close_connections=False)
                    for conn in list(self._all):
                        conn.close(1001, "going away")
                    await ws_server.wait_closed()
                for room in list(self.rooms.values()):
                    room.members.clear()
                    room.retire()
                    if room.recorder is not None:
                        tg.create_task(self._close_recorder(room))
                self.rooms.clear()
        finally:
            # Every room's recording is finished (the task group waited for them);
            # after a failure, rooms still open keep their .part for recovery.
            await self._close_hosts()

    # -- statistics ----------------------------------------------------------------------

    def statistics(self) -> dict[str, object]:
        conns = [c.statistics() for c in self._all]
        return {
            "connections": len(conns),
            "rooms": {name: room.statistics() for name, room in self.rooms.items()},
            "connection_stats": conns,
        }

    def metrics_text(self) -> str:
        """Prometheus text exposition of the server's counters."""
        conns = [c.statistics() for c in self._all]
        lines: list[str] = []

        def metric(name: str, kind: str, help_: str, samples: list[tuple[str, float]]) -> None:
            lines.append(f"# HELP {name} {help_}")
            lines.append(f"# TYPE {name} {kind}")
            for labels, value in samples:
                lines.append(f"{name}{labels} {_number(value)}")

        def total(*keys: str) -> list[tuple[str, float]]:
            # Ended connections plus live ones: a counter never goes down.
            return [("", sum(self.totals[k] + sum(getattr(c, k) for c in conns) for k in keys))]

        metric("posecast_connections", "gauge", "Open websocket connections.", [("", len(conns))])
        metric(
            "posecast_connections_closed_total",
            "counter",
            "Websocket connections that have ended.",
            [("", self.closed_connections)],
        )
        metric("posecast_rooms", "gauge", "Rooms with members.", [("", len(self.rooms))])
        metric(
            "posecast_recording_paused",
            "gauge",
            "1 while the recording of pose updates is paused (SIGUSR1; SIGUSR2 resumes).",
            [("", int(self.recording_paused))],
        )
        metric("posecast_frames_in_total", "counter", "Frames received.", total("frames_in"))
        metric("posecast_bytes_in_total", "counter", "Bytes received.", total("bytes_in"))
        metric("posecast_frames_out_total", "counter", "Frames sent.", total("frames_out"))
        metric("posecast_bytes_out_total", "counter", "Bytes sent.", total("bytes_out"))
        metric(
            "posecast_snapshot_skips_total",
            "counter",
            "Snapshots not delivered because a subscriber had not drained the previous one.",
            total("skips", "congestion_skips"),
        )
        metric(
            "posecast_flood_drops_total",
            "counter",
            "Pose updates and events dropped for exceeding the per-connection rate.",
            total("flood_drops"),
        )
        metric(
            "posecast_event_drops_total",
            "counter",
            "Reliable messages refused by a full event queue (the connection is closed).",
            total("event_drops"),
        )
        metric(
            "posecast_protocol_errors_total",
            "counter",
            "Protocol errors detected in what clients sent.",
            total("protocol_errors"),
        )
        rooms = [r.statistics() for r in self.rooms.values()]
        metric(
            "posecast_room_members",
            "gauge",
            "Members per room.",
            [(f'{{room="{_label(r.name)}"}}', r.members) for r in rooms],
        )
        metric(
            "posecast_room_poses_out_total",
            "counter",
            "Poses sent in snapshots per room.",
            [(f'{{room="{_label(r.name)}"}}', r.poses_out) for r in rooms],
        )
        metric(
            "posecast_room_tick_lag_max_ms",
            "gauge",
            "Largest delay of a room tick behind its due time.",
            [(f'{{room="{_label(r.name)}"}}', r.tick_lag_max_ms) for r in rooms],
        )
        return "\n".join(lines) + "\n"


def _number(value: float) -> str:
    """A sample value: integers exactly (``:g`` would round 1234567 to 1.23457e+06)."""
    if isinstance(value, int) or (math.isfinite(value) and value == int(value)):
        return str(int(value))
    if math.isnan(value):
        return "NaN"
    if math.isinf(value):
        return "+Inf" if value > 0 else "-Inf"
    return repr(float(value))


def _label(value: str) -> str:
    return value.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")
