"""Headless bot: publish a motion, receive everyone else's, render at 90 Hz.

A bot connects, syncs its clock with the server (several pings, lowest round
trip kept, refreshed periodically), joins with a motion label, then runs four
tasks under one ``TaskGroup``: publisher (its motion at the send rate, capture
times in server time), receiver (snapshots into per-stream jitter buffers and
an arrival log), renderer (every remote stream at ``server_now - D`` in one
batched call per interpolator) and pinger. D is the room's
(:class:`client.playout.RoomPlayoutDelay`): a peer whose keyframes arrive
persistently late (its clock is off, its path is slow) does not raise it, and
is shown late alone, at its own D, in the same batched call. At the end it
scores what it received with :mod:`scenarios.qoe`, exactly as DESIGN.md
defines it, each stream with the D it was rendered with.

A session ends in one of three ways, recorded in :class:`SessionEnd`: it ran its
duration (``complete``), the server closed the connection with a close frame
(``closed``: e.g. 1001 "going away" when it shuts down) or the connection broke
without one (``lost``: the server was killed, the network went away). In every
case the bot scores and reports what it received until then; only failing to
connect at all, or a refused join, is an exception. After a drop (or a close
1012, or 1001 when it has other relays: ``BotConfig.urls``) it reconnects, to the
relay it was on and then the others in order, cycling, for ``resume_window``: it
resumes where its session is held and rejoins as a new member where it is not
(its peers' streams from before are scored until the rejoin).

The render loop also notes how often it ran late: a frame is *late* when it
started more than one render period (1/90 s) after its scheduled time, i.e. it
missed the display slot a headset would have shown it in (the loop then catches
up; it never skips). A share of late frames is a sign of a starved machine (see
:func:`client.swarm.starvation`).

Velocity keyframes: when a rendered method needs them (``motor-hermite``) or
``BotConfig.velocities`` says so, the bot joins with ``sends_velocities`` and
``wants_velocities``: it publishes each pose with the velocity a tracker runtime
could report at capture time (:meth:`scenarios.traces.Trace.causal_velocities`,
past native samples only), receives velocity snapshots, keeps the velocities in
its buffers and arrival log, and renders and scores velocity methods from them
(streams of peers that send no velocities arrive with zeros, and velocity
methods render and score those streams with ``motor-lerp`` instead).

Codec: with ``BotConfig.codec == "compact"`` (the default) the bot joins with
``codec="compact"``: its session codes each update with the compact codec
(``protocol.codec``: quantised, delta-coded per stream) and decodes the relay's
compact snapshots (``protocol.codec_relay``), which leave its own streams out;
``raw`` sends and receives float records as before. The report counts the bytes
of the update frames it sent and the poses in them (``update_bytes``,
``poses_sent``), and the snapshot bytes it received.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from websockets.exceptions import ConnectionClosed

import posecast.client.remote as scoring
from posecast.client.buffers import RoomBuffers
from posecast.client.connection import ClientConnection, SessionEnd, Tls, connect_any, connect_first
from posecast.client.playout import ClockEstimator, RoomPlayoutDelay
from posecast.client.remote import RemoteStream, evaluate_remote, remote_log, stream_delays
from posecast.client.render import render_buffers
from posecast.client.scene import OwnerChange, ThrowCatchActor
from posecast.interp import info as interp_info
from posecast.protocol import (
    ROOM_USER,
    Joined,
    LocalProtocolError,
    Owner,
    PeerJoined,
    PeerLeft,
    Ping,
    Pong,
    PoseUpdate,
    Snapshot,
    encode_update,
)
from posecast.scenarios.motion import MotionSpec, SpawnPoint, sample_at
from posecast.scenarios.qoe import ErrorSamples
from posecast.scenarios.throw_catch import SCENE, role_motion, scene_epoch, scene_role
from posecast.scenarios.traces import (
    CAUSAL_SAMPLES,
    DEVICE_NAMES,
    Trace,
    TraceError,
    causal_velocities,
    find_traces,
)

__all__ = [
    "BotConfig",
    "BotReport",
    "RemoteStream",
    "SessionEnd",
    "motion_for_bot",
    "remote_log",
    "run_bot",
    "stream_delays",
]

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class BotConfig:
    #: The relay it connects to (``ws://`` or ``wss://``); may be left out for ``urls``.
    url: str = ""
    room: str = "lobby"
    #: Snapshot rate asked of the server (Hz).
    rate: float = 15.0
    #: How often the bot publishes its own poses (Hz).
    send_rate: float = 30.0
    methods: tuple[str, ...] = ("soa", "dq-slerp", "motor-lerp")
    #: A trace CSV path or ``synthetic:NAME``; the seed varies synthetic motion.
    motion: str = "synthetic:orbit"
    seed: int = 0
    duration: float = 10.0
    render_rate: float = 90.0
    token: str | None = None
    name: str = "bot"
    ping_interval: float = 1.0
    initial_pings: int = 8
    #: Keep every rendered frame (first method) for inspection; memory grows.
    keep_render_log: bool = False
    #: Send velocity keyframes and receive velocity snapshots. None: exactly when a
    #: rendered method needs keyframe velocities.
    velocities: bool | None = None
    #: How the bot's poses are coded both ways (``Join.codec``): ``compact`` (updates
    #: as codec frames, snapshots as relay delta frames) or ``raw`` float records.
    codec: str = "compact"
    #: For a ``wss://`` URL: trust this CA file (PEM), or check nothing (tests only).
    cafile: str | None = None
    insecure: bool = False
    #: Seconds added to the bot's estimate of the server clock: it stamps its
    #: captures that far off (a member whose clock is wrong; tests and benches).
    clock_error: float = 0.0
    #: Ask the server to keep its place if the connection drops (``hello.resumable``)
    #: and, if it does, reconnect with the resume token and go on as the same user.
    resume: bool = True
    #: How long it tries to reconnect (s): the server keeps a place this long (10 s).
    resume_window: float = 10.0
    #: Relays to fail over to (the nodes of a cluster, or spares): see :attr:`relays`.
    urls: tuple[str, ...] = ()
    spawn: SpawnPoint | None = None  # its motion moved there (scenarios.spawn); None: not
    auto_rate: bool = False  # join rate "auto": the relay chooses it, up to ``rate``

    @property
    def relays(self) -> tuple[str, ...]:
        """The relays in the order the bot tries them: ``url`` (else ``urls[0]``) first,
        then the others of ``urls`` after it, cycling."""
        urls, url = self.urls, self.url
        if url and url not in urls:
            return (url, *urls)
        i = urls.index(url) if url else 0
        return urls[i:] + urls[:i]


@dataclass
class BotReport:
    """What one bot measured."""

    user: int
    name: str
    qoe: dict[str, dict[str, ErrorSamples]]
    #: New keyframes received per remote stream per second (mean over streams).
    rate_hz: float
    delay_ms: float
    render_stall_fraction: float
    frames_rendered: int
    render_cpu_s: float
    snapshot_bytes: int
    poses_received: int
    bytes_in: int
    bytes_out: int
    duration: float
    clock_rtt_ms: float
    #: Snapshot age at arrival (send time -> receipt; ms: p50, p99), longest gap (s).
    snapshot_age_ms: tuple[float, float] = (float("nan"), float("nan"))
    snapshot_gap_s: float = float("nan")
    #: Whether it sent and received velocity keyframes (snapshot bytes include them).
    velocities: bool = False
    #: Upstream codec (``raw`` or ``compact``), bytes of the update frames it sent
    #: (websocket framing excluded) and the poses in them.
    codec: str = "raw"
    update_bytes: int = 0
    poses_sent: int = 0
    #: Render frames that started over one render period after their scheduled time.
    frames_late: int = 0
    #: Snapshot rate asked and granted (Hz; an auto rate's last), and the rate it published at.
    asked_hz: float = 0.0
    granted_hz: float = 0.0
    send_hz: float = 0.0
    #: How the session ended (see :class:`SessionEnd`).
    ending: SessionEnd = field(default_factory=SessionEnd)
    #: Peers shown late alone (``delay_ms`` is the room's D, everyone else's): their
    #: mean own D over the frames that showed them late, ms.
    late_delay_ms: dict[int, float] = field(default_factory=dict)
    #: Shared objects changing hands (``owner`` messages), in the order received.
    ownership: list[OwnerChange] = field(default_factory=list)
    #: Its role in the live throw-catch scene (``thrower``, ``catcher``, ``watcher``).
    role: str | None = None
    #: After drops: times it resumed, times it rejoined as a new member (a relay that
    #: did not hold its session; ``user`` is its last id), the relay it ended on.
    resumed: int = 0
    rejoined: int = 0
    relay: str = ""
    streams: dict[tuple[int, int], RemoteStream] = field(default_factory=dict, repr=False)
    #: With ``keep_render_log``: (the room's playout time, the room's D, bot clock at
    #: render, {stream key: (pose, stalled)}); a stream shown late alone at frame
    #: ``i`` was rendered at its own D (``RemoteStream.own_delays``), i.e. at playout
    #: time ``t_play + D - own D``.
    render_log: list[tuple[float, float, float, dict[tuple[int, int], tuple[F64, bool]]]] = field(
        default_factory=list, repr=False
    )


def motion_for_bot(spec: str, index: int) -> tuple[str, int]:
    """Resolve ``--motion`` for bot ``index``: (trace path or synthetic:NAME, seed).

    ``throw-catch``: the live scene, bot 0 throws, bot 1 catches, the others watch
    (one shared seed: they play one script)."""
    if spec == SCENE:
        return f"synthetic:{role_motion(index)}", 0
    if spec.startswith("synthetic"):
        name = spec.partition(":")[2] or "orbit"
        return f"synthetic:{name}", 0 if scene_role(name) else index
    files = find_traces(spec)
    return str(files[index % len(files)]), 0


class _CausalVelocities:
    """The causal velocity of each native sample of a trace, computed when first needed.

    Equal to ``trace.causal_velocities()[i]`` (the estimate at sample ``i`` only
    uses samples ``i - CAUSAL_SAMPLES + 1 .. i``), computed a chunk of samples at
    a time: a few milliseconds now and then instead of the whole trace up front.
    """

    CHUNK = 256

    def __init__(self, trace: Trace) -> None:
        self.trace = trace
        self._chunks: dict[int, NDArray[np.float64]] = {}

    def __getitem__(self, i: int) -> NDArray[np.float64]:
        c, k = divmod(i, self.CHUNK)
        chunk = self._chunks.get(c)
        if chunk is None:
            lo = c * self.CHUNK
            start = max(0, lo - (CAUSAL_SAMPLES - 1))  # the history the first sample needs
            hi = lo + self.CHUNK
            tr = self.trace
            chunk = causal_velocities(tr.times[start:hi], tr.poses[start:hi])[lo - start :]
            self._chunks[c] = chunk
        row: NDArray[np.float64] = chunk[k]
        return row


class _Bot:
    def __init__(self, cfg: BotConfig, clock: Callable[[], float]) -> None:
        self.cfg = cfg
        self.clock = clock
        self.tls = Tls(cfg.cafile, cfg.insecure)
        self.est = ClockEstimator()
        needs = [m for m in cfg.methods if interp_info(m).needs_velocity]
        self.velocities = bool(needs) if cfg.velocities is None else cfg.velocities
        if needs and not self.velocities:
            raise ValueError(f"{', '.join(needs)} need keyframe velocities (velocities=False)")
        #: Causal velocities of the bot's own motion at its native samples, if it sends them.
        self.send_velocities: _CausalVelocities | None = None
        # A window method waits for the keyframe after the bracket: one more interval.
        lookahead = max(interp_info(m).lookahead for m in cfg.methods)
        self.delay = RoomPlayoutDelay(interval=(1.0 + lookahead) / cfg.rate, rate=cfg.rate)
        self.remote: dict[tuple[int, int], RemoteStream] = {}
        #: Each remote user's streams (their rows share the user's D).
        self.user_streams: dict[int, list[RemoteStream]] = {}
        #: Every remote stream's render buffer, one row each, in ``remote``'s order.
        self.room_buffers = RoomBuffers()
        self.peers: dict[int, tuple[dict[int, str], str | None]] = {}
        #: Peers whose updates carry velocities (peer_joined.velocities).
        self.velocity_peers: set[int] = set()
        self.play_t: list[float] = []
        self.play_d: list[float] = []
        self.render_stalls = self.render_samples = self.frames = self.frames_late = 0
        self.render_cpu, self.ping_seq = 0.0, 0
        self.snapshot_bytes = self.poses_in = self.update_bytes = self.poses_sent = 0
        self.snapshot_times: list[tuple[float, float]] = []  # arrival, send: server clock
        self.conn: ClientConnection | None = None
        #: The bot's part in the live throw-catch scene, if it plays one.
        self.actor: ThrowCatchActor | None = None
        #: Every ``owner`` message received (shared objects changing hands), in order.
        self.ownership: list[OwnerChange] = []
        self._seq = 0
        self._last_sample = -1.0
        self.render_log: list[
            tuple[float, float, float, dict[tuple[int, int], tuple[F64, bool]]]
        ] = []
        self.trace: Trace | None = None
        self.spec: MotionSpec | None = None
        #: The bot's clock when the session started (set on connecting, then after sync).
        self.started_local = 0.0
        #: Set when the connection closed before the session's end.
        self.ending: SessionEnd | None = None
        #: Set when the connection dropped and the bot may resume (``BotConfig.resume``).
        self.lost = asyncio.Event()
        #: The close that made it reconnect (None: a drop): its ending if that fails.
        self.dropped: SessionEnd | None = None
        #: Connections resumed after a drop, and when each resumed (bot clock).
        self.resumed_at: list[float] = []
        #: Rejoins as a new member (bot clock); the relay it is on (index in cfg.relays).
        self.rejoined_at: list[float] = []
        self.relay = 0
        #: Streams scored until a render frame only (a peer left; see _retire).
        self.until: dict[tuple[int, int], int] = {}

    def server_now(self) -> float:
        return self.clock() + self.est.offset + self.cfg.clock_error

    def _note_closed(self, exc: ConnectionClosed) -> None:
        """Remember how the connection ended (the first report of it wins)."""
        if self.ending is not None:
            return
        after = max(0.0, self.clock() - self.started_local)
        rcvd = exc.rcvd
        if self._reconnects(None if rcvd is None else rcvd.code):
            self.lost.set()  # _connected reconnects: resumes, or rejoins elsewhere
            self.dropped = None if rcvd is None else SessionEnd("closed", 0, rcvd.code, rcvd.reason)
            return
        if rcvd is not None:
            self.ending = SessionEnd("closed", after, rcvd.code, rcvd.reason)
        else:
            self.ending = SessionEnd("lost", after)

    def _reconnects(self, code: int | None) -> bool:
        """Whether a joined session goes on after its connection ended: a drop (``code``
        None) with a resume token or other relays; a relay going away (1001) with others;
        a cluster node that asks its clients to reconnect (1012, its room's owner died)."""
        conn, cfg = self.conn, self.cfg
        if not cfg.resume or conn is None or conn.welcome is None or conn.joined is None:
            return False
        several = len(cfg.relays) > 1
        if code is None:
            return several or conn.welcome.resume is not None
        return code == 1012 or (several and code == 1001)

    async def _sync(self, conn: ClientConnection, n: int) -> None:
        for _ in range(n):
            self.ping_seq += 1
            await conn.send(Ping(seq=self.ping_seq, time=self.clock()))
            while True:
                rec = await conn.recv()
                if isinstance(rec.event, Pong):
                    self.est.add(rec.event.offset(rec.arrival), rec.event.round_trip(rec.arrival))
                    break
                self._on_event(rec.event, rec.arrival, rec.size)

    def _add_peer(self, ev: PeerJoined) -> None:
        if any(user == ev.user for user, _ in self.until):  # the id of one that left
            self._retire({ev.user}, rekey=True)
        self.peers[ev.user] = ({sid: name for name, sid in ev.streams.items()}, ev.label)
        if ev.velocities:
            self.velocity_peers.add(ev.user)
            for (user, _sid), rs in self.remote.items():  # snapshots that came first
                if user == ev.user:
                    rs.sends_velocities = rs.buffer.has_velocities = True

    def _on_event(self, ev: object, arrival: float, size: int) -> None:
        if isinstance(ev, Snapshot):
            self._on_snapshot(ev, arrival, size)
        elif isinstance(ev, Pong):
            self.est.add(ev.offset(arrival), ev.round_trip(arrival))
        elif isinstance(ev, PeerJoined):
            self._add_peer(ev)
        elif isinstance(ev, PeerLeft):
            self._retire({ev.user})
        elif isinstance(ev, Owner):
            self.ownership.append(OwnerChange(ev.time, ev.stream, ev.owner, ev.previous, ev.reason))
            if self.actor is not None and self.conn is not None:
                self.actor.on_owner(ev, self.conn.user)

    def _retire(self, users: set[int], *, rekey: bool = False) -> None:
        """Score ``users``' streams until this render frame only: a peer left, or the bot
        left their relay. ``rekey``: key them apart (over every key), for new members
        with those ids (the next relay's, or one reused)."""
        frame, remote = len(self.play_t), {}
        shift = ((max((u for u, _ in self.remote), default=0) >> 16) + 1) << 16 if rekey else 0
        for key, rs in self.remote.items():  # in order: the order of the render rows
            if key[0] in users:  # one that left before keeps its end
                end, key = self.until.pop(key, frame), (key[0] + shift, key[1])
                self.until[key] = end
            remote[key] = rs
        self.remote = remote
        for user in users:
            self.peers.pop(user, None)
            self.user_streams.pop(user, None)
            self.velocity_peers.discard(user)
            self.delay.forget(user)

    def _sends_velocities(self, user: int) -> bool:
        """Whether ``user``'s keyframes come with velocities: a peer that said so; the
        scene's drill when the scene's bots send them (the relay's flight keyframes
        always carry the flight's exact velocity)."""
        if user == ROOM_USER:
            return self.actor is not None and self.velocities
        return user in self.velocity_peers

    def _names(self, user: int) -> tuple[dict[int, str], str | None]:
        """A remote user's stream names and motion label; for the room's objects
        (``ROOM_USER``) their names, and the scene's drill label if in the scene."""
        if user != ROOM_USER:
            return self.peers.get(user, ({}, None))
        objects = {} if self.conn is None else self.conn.session.objects
        names = {sid: name for name, sid in objects.items()}
        return names, None if self.actor is None else self.actor.label

    def _on_snapshot(self, snap: Snapshot, arrival: float, size: int) -> None:
        me = self.conn.user if self.conn else -1
        arrival_srv = arrival + self.est.offset
        users, streams = snap.users, snap.streams
        caps, poses = snap.capture_times, snap.poses
        sent = snap.send_time
        vels = snap.velocities
        vel64 = None if vels is None else vels.astype(np.float64)
        self.snapshot_bytes += size
        self.snapshot_times.append((arrival_srv, sent))
        floor = self.play_t[-1] if self.play_t else -np.inf
        for i in range(len(snap)):
            user = int(users[i])
            if user == me:
                continue
            key = (user, int(streams[i]))
            rs = self.remote.get(key)
            if rs is None:
                names, label = self._names(user)
                rs = self.remote[key] = RemoteStream(
                    user, key[1], names.get(key[1], f"stream{key[1]}"), label,
                    sends_velocities=self._sends_velocities(user),
                    buffer=self.room_buffers.stream(),
                )  # fmt: skip
                self.user_streams.setdefault(user, []).append(rs)
            cap, pose = float(caps[i]), np.array(poses[i])
            if rs.repeats(cap, pose):
                continue
            self.poses_in += 1
            rs.capture.append(cap)
            rs.arrival.append(arrival_srv)
            rs.arrival_local.append(arrival)
            rs.sent.append(sent)
            rs.poses.append(pose)
            vel = None
            if vel64 is not None:
                vel = vel64[i]
                rs.velocities.append(vel)
            rs.buffer.push(cap, pose, floor, vel)
            self.delay.observe(user, arrival_srv - cap)

    async def _publish(self, conn: ClientConnection, stop: float) -> None:
        try:
            await self._publish_until(conn, stop)
        except ConnectionClosed as exc:
            self._note_closed(exc)
        except LocalProtocolError:
            if not conn.session.closed:
                raise
            # The server ended the session (bye, fatal error); its close frame follows.

    async def _publish_until(self, conn: ClientConnection, stop: float) -> None:
        assert self.spec is not None
        t0, actor = self.spec.t0, self.actor
        period = 1.0 / self.cfg.send_rate
        self._seq, self._last_sample = 0, -1.0  # per connection, as the session counts
        k, nxt = 0, -np.inf
        while True:
            now = self.server_now()
            if now >= stop:
                return
            if actor is not None:  # the scene's actions, each at its own time
                for at, action in actor.due(now):
                    await actor.perform(conn, action, at, partial(self._send_sample, conn), now)
            if now >= nxt:
                await self._send_sample(conn, now)
                k += 1
                nxt = t0 + k * period
                if nxt <= now:  # fell behind: resume on the grid, never burst
                    k = int((now - t0) / period) + 1
                    nxt = t0 + k * period
            wake = nxt if actor is None else min(nxt, actor.next_at())
            await asyncio.sleep(max(0.0, wake - self.server_now()))

    async def _send_sample(self, conn: ClientConnection, now: float) -> None:
        """Publish the newest sample at server time ``now``, unless it was sent (with the
        scene's object while this bot holds it)."""
        assert self.trace is not None and self.spec is not None and conn.joined is not None
        trace, t0, vel = self.trace, self.spec.t0, self.send_velocities
        idx, tm = sample_at(trace, max(0.0, now - t0))
        if tm == self._last_sample:
            return
        self._last_sample = tm
        cap = t0 + tm
        self._seq += 1
        ids = np.array([conn.joined.streams[n] for n in trace.streams])
        poses = trace.poses[idx]
        velocities = None if vel is None else vel[idx]
        drill = None if self.actor is None else self.actor.publishing(conn, cap)
        if self.actor is not None and drill is not None:
            ids = np.append(ids, drill)
            poses = np.concatenate([poses, self.actor.drill.poses[idx]])
            if velocities is not None:
                velocities = np.concatenate([velocities, self.actor.velocity(idx)[None]])
        before = conn.bytes_out
        args = (self._seq, ids, np.full(ids.size, cap), poses.astype(np.float32))
        if self.cfg.codec == "raw":
            await conn.send_bytes(encode_update(*args, base_time=cap, velocities=velocities))
        else:  # the session codes it, against what it sent before
            await conn.send(PoseUpdate.from_arrays(*args, base_time=cap, velocities=velocities))
        self.update_bytes += conn.bytes_out - before
        self.poses_sent += ids.size

    async def _receive(self, conn: ClientConnection) -> None:
        try:
            while True:
                rec = await conn.recv()
                self._on_event(rec.event, rec.arrival, rec.size)
        except ConnectionClosed as exc:
            self._note_closed(exc)

    async def _render(self, stop: float) -> None:
        period = 1.0 / self.cfg.render_rate
        methods = self.cfg.methods
        nxt = self.clock()
        while self.ending is None and self.server_now() < stop:
            local = self.clock()
            if local - nxt > period:  # missed its display slot
                self.frames_late += 1
            now_srv = local + self.est.offset
            d = self.delay.update(now_srv)
            t_play = now_srv - d
            c0 = time.process_time()
            frame = render_buffers(self.room_buffers, self._row_times(now_srv, d), methods)
            self.render_cpu += time.process_time() - c0
            if self.cfg.keep_render_log:
                keys = [k for k, rs in self.remote.items() if len(rs.buffer)]
                first, stalled = frame.poses[methods[0]], frame.stalled
                shown = {k: (first[j], bool(stalled[j])) for j, k in enumerate(keys)}
                self.render_log.append((t_play, d, local, shown))
            self.frames += 1
            self.render_stalls += int(frame.stalled.sum())
            self.render_samples += frame.stalled.size
            self.play_t.append(t_play)
            self.play_d.append(d)
            nxt += period
            await asyncio.sleep(max(0.0, nxt - self.clock()))

    def _row_times(self, now_srv: float, d: float) -> float | F64:
        """This frame's playout time: the room's, or one per row when a peer is shown
        late alone (noted in its streams' ``own_delays``)."""
        own = self.delay.own
        if not own:
            return now_srv - d
        frame = len(self.play_t)
        d_rows = np.full(len(self.room_buffers), d)
        for user, d_own in own.items():
            for rs in self.user_streams.get(user, ()):
                d_rows[rs.buffer.row] = d_own
                rs.own_delays.append((frame, d_own))
        return now_srv - d_rows

    async def _pinger(self, conn: ClientConnection, stop: float) -> None:
        try:
            while self.server_now() < stop:
                await asyncio.sleep(self.cfg.ping_interval)
                self.ping_seq += 1
                await conn.send(Ping(seq=self.ping_seq, time=self.clock()))
        except ConnectionClosed as exc:
            self._note_closed(exc)
        except LocalProtocolError:
            if not conn.session.closed:
                raise

    async def run(self) -> BotReport:
        cfg = self.cfg
        self.relay, conn = await connect_any(
            cfg.relays, clock=self.clock, agent=cfg.name, tls=self.tls, resumable=cfg.resume
        )
        self.conn, self.started_local = conn, self.clock()
        start = self.server_now()
        try:
            await self._session(conn)
        except ConnectionClosed as exc:  # while syncing or joining
            self._note_closed(exc)
        finally:
            # The connection it ends on (a resumed one, after a drop): a close frame,
            # so the server knows it left rather than dropped.
            with contextlib.suppress(ConnectionClosed):
                await (self.conn or conn).close()
        if self.spec is not None:
            start = self.spec.t0
        # Loading the peers' ground truth and scoring it is heavy: off the loop,
        # so other bots (and an in-process server) keep their timing.
        return await asyncio.to_thread(self._report, start)

    async def _session(self, conn: ClientConnection) -> None:
        """Sync, join and run the session; returns at its end or when the connection ends."""
        cfg = self.cfg
        await self._sync(conn, cfg.initial_pings)
        self.started_local, start = self.clock(), self.server_now()
        source, seed = cfg.motion, cfg.seed
        role = scene_role(source.partition(":")[2])
        if role is not None:  # one script on server time: every bot's t0 on its grid
            if role == "drill":
                raise TraceError("throw-catch.drill is the drill's motion, no bot's")
            self.spec = MotionSpec(source, seed, scene_epoch(start))
            self.actor = ThrowCatchActor(role, seed, self.spec.t0, start)
        elif source.startswith("synthetic:"):
            self.spec = MotionSpec(source, seed, start)
        else:
            self.spec = MotionSpec.for_trace(Path(source), start)
        # Reading a trace CSV takes a while: not on the event loop.
        self.spec = await asyncio.to_thread(self.spec.placed, cfg.spawn, conn.session.volume)
        motion = await asyncio.to_thread(self.spec.load)
        self.trace = motion.select(DEVICE_NAMES)
        if self.velocities:
            self.send_velocities = _CausalVelocities(self.trace)
        await self._join(conn, self.spec.label())
        for ev in conn.early_peers:
            self._add_peer(ev)
        stop = start + cfg.duration
        async with asyncio.TaskGroup() as tg:
            link = tg.create_task(self._connected(conn, stop))
            # The render loop ends at ``stop`` or as soon as the connection ended.
            await self._render(stop)
            link.cancel()

    async def _join(self, conn: ClientConnection, label: str | None) -> Joined:
        cfg, streams = self.cfg, self.trace.streams if self.trace is not None else ()
        conn.on_rate = self.delay.retime  # the relay chose another rate (``auto_rate``)
        return await conn.join(
            room=cfg.room,
            streams=streams,
            rate=cfg.rate,
            auto_rate=cfg.auto_rate,
            token=cfg.token,
            label=label,
            sends_velocities=self.velocities,
            wants_velocities=self.velocities,
            codec=cfg.codec,
        )

    async def _connected(self, conn: ClientConnection, stop: float) -> None:
        """Receive, publish and ping on ``conn``; after a drop, resume on a new one."""
        while True:
            self.lost.clear()
            async with asyncio.TaskGroup() as tg:
                tasks = [
                    tg.create_task(self._receive(conn)),
                    tg.create_task(self._publish(conn, stop)),
                    tg.create_task(self._pinger(conn, stop)),
                ]
                await self.lost.wait()
                for task in tasks:
                    task.cancel()
            resumed = await self._resume(conn, stop)
            if resumed is None:
                return
            conn = resumed

    async def _resume(self, old: ClientConnection, stop: float) -> ClientConnection | None:
        """Reconnect after a drop, within the resume window: to the relay it was on,
        then the next ones of ``cfg.relays`` in order, cycling. A relay that holds its
        session resumes it (the same user and streams); one that does not takes it
        back as a new member (a rejoin: the same room, streams and motion, a new user
        id; its peers see it leave and join). None if the window closed first, or its
        one relay refused the join: the session ends as lost (or closed, as it was)."""
        cfg, welcome, joined = self.cfg, old.welcome, old.joined
        assert welcome is not None and joined is not None
        assert self.trace is not None and self.spec is not None
        with contextlib.suppress(Exception):
            await old.ws.close()
        after = max(0.0, self.clock() - self.started_local)
        relays = cfg.relays
        give_up = min(stop, self.server_now() + cfg.resume_window)
        while True:
            found = await connect_first(
                relays,
                self.relay,
                self.clock() + give_up - self.server_now(),
                clock=self.clock,
                agent=cfg.name,
                tls=self.tls,
                resumable=True,
                resume=welcome.resume,
            )
            if found is None:
                break
            i, conn = found
            resumed = conn.welcome is not None and conn.welcome.resumed
            try:  # a rejoin says what it plays, as at the start
                again = await self._join(conn, None if resumed else self.spec.label())
                if resumed and again.streams != joined.streams:
                    raise ConnectionError("the resumed join got other stream ids")
            except Exception:  # refused, or the relay went away meanwhile
                with contextlib.suppress(Exception):
                    await conn.close()
                if len(relays) == 1:
                    break
                self.relay = (i + 1) % len(relays)
                continue
            self.relay = i
            if resumed:
                self.resumed_at.append(self.clock())
            else:  # everyone it knew is on the relay it left (16-bit ids, as here)
                self._retire({user for user, _ in self.remote if user <= ROOM_USER}, rekey=True)
                self.rejoined_at.append(self.clock())
            self.conn = conn
            for ev in conn.early_peers:
                self._add_peer(ev)
            return conn
        self.ending = replace(self.dropped or SessionEnd("lost"), after_s=after)
        return None

    def _score(self) -> dict[str, dict[str, ErrorSamples]]:
        """QoE of every stream over the frames it was shown for: to the end, or for a
        peer that left (and every peer of a relay the bot left) until then."""
        methods, n = self.cfg.methods, len(self.play_t)
        groups: dict[int, dict[tuple[int, int], RemoteStream]] = {}
        for key, rs in self.remote.items():
            groups.setdefault(self.until.get(key, n), {})[key] = rs
        out: dict[str, dict[str, ErrorSamples]] = {m: {} for m in methods}
        for k, streams in groups.items():
            part = evaluate_remote(streams, self.play_t[:k], self.play_d[:k], methods)
            for m, classes in part.items():
                for cls, samples in classes.items():
                    out[m].setdefault(cls, ErrorSamples()).merge(samples)
        return out

    def _report(self, start: float) -> BotReport:
        cfg, qoe = self.cfg, self._score()
        end = self.play_t[-1] + self.play_d[-1] if self.play_t else start
        span = max(1e-9, end - start)
        # Per stream: new keyframes per second over the span it was received.
        rates = [
            (len(set(rs.capture)) - 1) / (rs.arrival[-1] - rs.arrival[0])
            for rs in self.remote.values()
            if len(rs.arrival) > 1 and rs.arrival[-1] > rs.arrival[0]
        ]
        assert self.conn is not None
        return BotReport(
            user=self.conn.user,
            name=cfg.name,
            qoe=qoe,
            rate_hz=float(np.mean(rates)) if rates else 0.0,
            delay_ms=1000.0 * float(np.mean(self.play_d)) if self.play_d else float("nan"),
            render_stall_fraction=self.render_stalls / max(1, self.render_samples),
            frames_rendered=self.frames,
            render_cpu_s=self.render_cpu,
            snapshot_bytes=self.snapshot_bytes,
            poses_received=self.poses_in,
            bytes_in=self.conn.bytes_in,
            bytes_out=self.conn.bytes_out,
            duration=span,
            clock_rtt_ms=1000.0 * self.est.rtt,
            snapshot_age_ms=scoring.p50_p99_ms([a - s for a, s in self.snapshot_times]),
            snapshot_gap_s=scoring.longest_gap([a for a, _ in self.snapshot_times]),
            velocities=self.velocities,
            codec=cfg.codec,
            update_bytes=self.update_bytes,
            poses_sent=self.poses_sent,
            frames_late=self.frames_late,
            asked_hz=cfg.rate,
            granted_hz=self.conn.session.rate or cfg.rate,  # an auto rate's last choice
            send_hz=cfg.send_rate,
            ending=self.ending or SessionEnd("complete", max(0.0, end - start)),
            late_delay_ms={
                user: 1000.0 * float(np.mean([d for _, d in streams[0].own_delays]))
                for user, streams in self.user_streams.items()
                if streams[0].own_delays
            },
            ownership=self.ownership,
            role=None if self.actor is None else self.actor.role,
            resumed=len(self.resumed_at),
            rejoined=len(self.rejoined_at),
            relay=cfg.relays[self.relay],
            streams=self.remote,
            render_log=self.render_log,
        )


async def run_bot(cfg: BotConfig, clock: Callable[[], float] = time.monotonic) -> BotReport:
    """Run one bot to the end of its duration and return what it measured."""
    return await _Bot(cfg, clock).run()
