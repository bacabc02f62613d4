"""Headless bot: publish a motion, receive everyone else's, render at 90 Hz.

:class:`Bot` is an asyncio adapter over the sans-I/O client core
(:class:`client.core.ClientCore`: clock estimate, jitter buffers, playout delay,
render) and the reconnect policy (:class:`client.reconnect.Reconnect`); it holds
no rule of its own. A bot connects, syncs its clock with the server (several
pings, lowest round trip kept, refreshed periodically), joins with a motion
label, then runs four tasks under one ``TaskGroup``: publisher
(:class:`client.publish.Publisher`: its motion at the send rate, capture times
in server time), receiver (:class:`client.receiver.Receiver`: events into the
core, whose observer :class:`client.log.SessionLog` logs arrivals for scoring),
renderer (every remote stream at ``server_now - D`` in one batched call per
interpolator) and pinger. D is the room's
(:class:`client.playout.RoomPlayoutDelay`): a peer whose keyframes arrive
persistently late (its clock is off, its path is slow) does not raise it, and
is shown late alone, at its own D, in the same batched call. At the end it
scores what it received with :mod:`scenarios.qoe`, exactly as DESIGN.md
defines it, each stream with the D it was rendered with.

A session ends in one of these ways, recorded in :class:`SessionEnd`: it ran its
duration with fresh poses (``complete``) or mostly without them (``stalled``: over
half its render time every remote stream was held), the server closed the connection
with a close frame (``closed``: e.g. 1001 "going away" when it shuts down) or the
connection broke without one (``lost``: the server was killed, the network went
away). In every case the bot scores and reports what it received until then; only
failing to connect at all, or a refused join, is an exception. After a drop (or a
close 1012, or 1001 when it has other relays: ``BotConfig.urls``) it reconnects, to
the relay it was on and then the others in order, cycling, for ``resume_window``: it
resumes where its session is held and rejoins as a new member where it is not (its
peers' streams from before are scored until the rejoin). Its connection is pinged
every 2.5 s and dropped when a pong is 2.5 s late (as the relay does), so a silently
dead path is noticed inside the resume window.

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
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from websockets.exceptions import ConnectionClosed

import posecast.client.remote as scoring
from posecast.client.connection import ClientConnection, SessionEnd, Tls, connect_any, connect_first
from posecast.client.core import ClientCore
from posecast.client.log import SessionLog
from posecast.client.publish import Publisher
from posecast.client.receiver import Listener, Receiver
from posecast.client.reconnect import Reconnect, ran_to_the_end
from posecast.client.remote import RemoteStream, evaluate_remote, remote_log, stream_delays
from posecast.client.scene import OwnerChange, ThrowCatchActor
from posecast.interp import info as interp_info
from posecast.protocol import Joined, LocalProtocolError, Owner
from posecast.scenarios.motion import MotionSpec, SpawnPoint
from posecast.scenarios.qoe import ErrorSamples
from posecast.scenarios.throw_catch import SCENE, role_motion, scene_epoch, scene_role
from posecast.scenarios.traces import DEVICE_NAMES, TraceError, find_traces

__all__ = [
    "Bot",
    "BotConfig",
    "BotReport",
    "RemoteStream",
    "SessionEnd",
    "evaluate_remote",
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
    #: Join with this error budget (degrees of visual angle, ``join.budget_deg``):
    #: the relay sends each peer at the lowest rate that keeps within it. None: off.
    budget_deg: float | None = None

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
    #: CPU time of its render calls (the render thread's own, ``time.thread_time``).
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
    #: It joined with rate "auto" (``asked_hz`` is its ceiling, ``granted_hz`` the last choice).
    auto_rate: bool = False
    send_hz: float = 0.0
    #: How the session ended (see :class:`SessionEnd`).
    ending: SessionEnd = field(default_factory=SessionEnd)
    #: Render time (s) that showed no fresh pose of anyone (every remote stream held
    #: past its newest keyframe): a dead path, or nobody sending.
    stale_s: float = 0.0
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


class Bot:
    """One headless bot: the asyncio adapter over a :class:`client.core.ClientCore`.

    It connects, syncs, joins, publishes (:class:`client.publish.Publisher`),
    receives (:class:`client.receiver.Receiver`), renders at ``render_rate`` and
    reconnects as its policy says (:class:`client.reconnect.Reconnect`); what it
    received and showed is logged by a :class:`client.log.SessionLog` (the core's
    observer) and scored at the end. Public surface: :meth:`run`, :meth:`stop`,
    :meth:`listen`, and the read-only state below.
    """

    def __init__(self, cfg: BotConfig, clock: Callable[[], float] = time.monotonic) -> None:
        self.cfg = cfg
        self.clock = clock
        self.tls = Tls(cfg.cafile, cfg.insecure)
        needs = [m for m in cfg.methods if interp_info(m).needs_velocity]
        self.velocities = bool(needs) if cfg.velocities is None else cfg.velocities
        if needs and not self.velocities:
            raise ValueError(f"{', '.join(needs)} need keyframe velocities (velocities=False)")
        self.log = SessionLog(cfg.methods, keep_render_log=cfg.keep_render_log)
        self.core = ClientCore(
            cfg.methods,
            cfg.rate,
            velocities=self.velocities,
            observer=self.log,
            per_peer=cfg.budget_deg is not None,
        )
        self.policy = Reconnect(cfg.relays, cfg.resume, cfg.resume_window)
        self.receiver = Receiver(self.core, self.policy, clock, ping_interval=cfg.ping_interval)
        self.receiver.listen(self._owner)
        #: The bot's part in the live throw-catch scene, if it plays one.
        self.actor: ThrowCatchActor | None = None
        self.publisher: Publisher | None = None
        self.spec: MotionSpec | None = None
        #: Every ``owner`` message received (shared objects changing hands), in order.
        self.ownership: list[OwnerChange] = []
        self.frames_late = 0
        self.render_cpu = 0.0

    # -- what others may read or do -----------------------------------------------

    @property
    def conn(self) -> ClientConnection | None:
        """The connection it is on (a new one after a reconnect)."""
        return self.receiver.conn

    @property
    def remote(self) -> dict[tuple[int, int], RemoteStream]:
        """Every remote stream it received, as logged for scoring."""
        return self.log.streams

    @property
    def ending(self) -> SessionEnd | None:
        """How its session ended (None while it runs, or after it ran its duration)."""
        return self.policy.ending

    @property
    def resumed_at(self) -> list[float]:
        return self.policy.resumed_at

    @property
    def rejoined_at(self) -> list[float]:
        return self.policy.rejoined_at

    def listen(self, listener: Listener) -> None:
        """Call ``listener`` with every event received (event, arrival, size)."""
        self.receiver.listen(listener)

    def stop(self) -> None:
        """End the session now as ``interrupted``: its render loop ends at its next
        frame, and it reports the time it ran."""
        started = self.receiver.started_local
        after = self.clock() - started if started else 0.0
        self.policy.finish(SessionEnd("interrupted", max(0.0, after)))

    def server_now(self) -> float:
        return self.core.server_time(self.clock()) + self.cfg.clock_error

    # -- the session --------------------------------------------------------------

    def _owner(self, ev: object, arrival: float, size: int) -> None:
        if isinstance(ev, Owner):
            self.ownership.append(OwnerChange(ev.time, ev.stream, ev.owner, ev.previous, ev.reason))
            if self.actor is not None and self.conn is not None:
                self.actor.on_owner(ev, self.conn.user)

    async def run(self) -> BotReport:
        cfg = self.cfg
        self.policy.relay, conn = await connect_any(
            cfg.relays, clock=self.clock, agent=cfg.name, tls=self.tls, resumable=cfg.resume
        )
        self.receiver.attach(conn)
        self.receiver.started_local = self.clock()
        start = self.server_now()
        try:
            await self._session(conn)
        except ConnectionClosed as exc:  # while syncing or joining
            self.receiver.closed(exc)
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

    async def _motion(self, conn: ClientConnection, start: float) -> Publisher:
        """The bot's motion, placed, loaded (off the loop) and ready to publish."""
        cfg = self.cfg
        source, seed = cfg.motion, cfg.seed
        role = scene_role(source.partition(":")[2])
        if role is not None:  # one script on server time: every bot's t0 on its grid
            if role == "drill":
                raise TraceError("throw-catch.drill is the drill's motion, no bot's")
            spec = MotionSpec(source, seed, scene_epoch(start))
            self.actor = ThrowCatchActor(role, seed, spec.t0, start)
            self.core.room_label = self.actor.label
            self.core.room_velocities = self.velocities
        elif source.startswith("synthetic:"):
            spec = MotionSpec(source, seed, start)
        else:
            spec = MotionSpec.for_trace(Path(source), start)
        # Reading a trace CSV takes a while: not on the event loop.
        self.spec = spec = await asyncio.to_thread(spec.placed, cfg.spawn, conn.session.volume)
        motion = await asyncio.to_thread(spec.load)
        trace = motion.select(DEVICE_NAMES)
        return Publisher(
            trace,
            spec,
            cfg.send_rate,
            codec=cfg.codec,
            velocities=self.velocities,
            actor=self.actor,
        )

    async def _session(self, conn: ClientConnection) -> None:
        """Sync, join and run the session; returns at its end or when the connection ends."""
        await self.receiver.sync(conn, self.cfg.initial_pings)
        self.receiver.started_local = self.clock()
        start = self.server_now()
        self.publisher = await self._motion(conn, start)
        await self._join(conn, self.publisher.spec.label())
        self.receiver.attach(conn)
        # Its duration in the room: a join the relay held (a recorded room's recorder
        # starting, a cluster claim) does not eat into it.
        stop = max(start, self.server_now()) + self.cfg.duration
        async with asyncio.TaskGroup() as tg:
            link = tg.create_task(self._connected(conn, stop))
            # The render loop ends at ``stop`` or as soon as the connection ended.
            await self._render(stop)
            link.cancel()

    async def _join(self, conn: ClientConnection, label: str | None) -> Joined:
        cfg = self.cfg
        streams = self.publisher.trace.streams if self.publisher is not None else ()
        conn.on_rate = self.core.delay.retime  # the relay chose another rate (``auto_rate``)
        return await conn.join(
            room=cfg.room,
            streams=streams,
            rate=cfg.rate,
            auto_rate=cfg.auto_rate,
            budget_deg=cfg.budget_deg,
            token=cfg.token,
            label=label,
            sends_velocities=self.velocities,
            wants_velocities=self.velocities,
            codec=cfg.codec,
        )

    async def _render(self, stop: float) -> None:
        """Every remote stream at ``server_now - D`` each render period (a frame that
        starts over a period after its slot counts as late; the loop never skips)."""
        period = 1.0 / self.cfg.render_rate
        core, log, keep = self.core, self.log, self.cfg.keep_render_log
        nxt = self.clock()
        while self.ending is None and self.server_now() < stop:
            local = self.clock()
            if local - nxt > period:  # missed its display slot
                self.frames_late += 1
            playout = core.playout(local)
            if keep:
                log.note_local(local)
                log.note_shown(core.shown())
            # This thread's CPU only: the process's would count other threads' work
            # (a bot that loads its motion or scores its session off the loop).
            c0 = time.thread_time()
            frame = core.render(playout, report=False)
            self.render_cpu += time.thread_time() - c0
            core.report(frame)
            nxt += period
            await asyncio.sleep(max(0.0, nxt - self.clock()))

    async def _publish(self, conn: ClientConnection, stop: float) -> None:
        assert self.publisher is not None
        try:
            await self.publisher.run(conn, stop, self.server_now)
        except ConnectionClosed as exc:
            self.receiver.closed(exc)
        except LocalProtocolError:
            if not conn.session.closed:
                raise
            # The server ended the session (bye, fatal error); its close frame follows.

    async def _connected(self, conn: ClientConnection, stop: float) -> None:
        """Receive, publish and ping on ``conn``; after a drop, resume on a new one."""
        receiver = self.receiver
        while True:
            receiver.lost.clear()
            async with asyncio.TaskGroup() as tg:
                tasks = [
                    tg.create_task(receiver.receive(conn)),
                    tg.create_task(self._publish(conn, stop)),
                    tg.create_task(receiver.ping(conn, stop)),
                ]
                await receiver.lost.wait()
                for task in tasks:
                    task.cancel()
            resumed = await self._resume(conn, stop)
            if resumed is None:
                return
            conn = resumed

    async def _resume(self, old: ClientConnection, stop: float) -> ClientConnection | None:
        """Reconnect after a drop, within the resume window (the policy's deadline): to
        the relay it was on, then the next ones of ``cfg.relays`` in order, cycling. A
        relay that holds its session resumes it (the same user and streams); one that
        does not takes it back as a new member (a rejoin: the same room, streams and
        motion, a new user id; its peers see it leave and join). None if the window
        closed first, or its one relay refused the join: the session ends as lost (or
        closed, as it was)."""
        cfg, policy, welcome, joined = self.cfg, self.policy, old.welcome, old.joined
        assert welcome is not None and joined is not None and self.publisher is not None
        with contextlib.suppress(Exception):
            await old.ws.close()
        after = self.receiver.after()
        give_up = policy.start(self.server_now(), stop)
        while True:
            found = await connect_first(
                policy.relays,
                policy.relay,
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
                again = await self._join(conn, None if resumed else self.publisher.spec.label())
                if resumed and again.streams != joined.streams:
                    raise ConnectionError("the resumed join got other stream ids")
            except Exception:  # refused, or the relay went away meanwhile
                with contextlib.suppress(Exception):
                    await conn.close()
                if not policy.refused(i):
                    break
                continue
            policy.reconnected(i, resumed, self.clock())
            if not resumed:  # everyone it knew is on the relay it left
                users = self.core.left_relay()
                self.log.left_relay(users)
            self.receiver.attach(conn)
            return conn
        policy.gave_up(after)
        return None

    def _report(self, start: float) -> BotReport:
        cfg, log, pub = self.cfg, self.log, self.publisher
        qoe = log.score()
        end = log.play_t[-1] + log.play_d[-1] if log.play_t else start
        span = max(1e-9, end - start)
        conn = self.conn
        assert conn is not None
        ending = self.ending or ran_to_the_end(max(0.0, end - start), log.stale_s)
        return BotReport(
            user=conn.user,
            name=cfg.name,
            qoe=qoe,
            rate_hz=log.keyframe_rate(),
            delay_ms=1000.0 * float(np.mean(log.play_d)) if log.play_d else float("nan"),
            render_stall_fraction=log.render_stalls / max(1, log.render_samples),
            frames_rendered=self.core.frames,
            render_cpu_s=self.render_cpu,
            snapshot_bytes=log.snapshot_bytes,
            poses_received=log.poses_in,
            bytes_in=conn.bytes_in,
            bytes_out=conn.bytes_out,
            duration=span,
            clock_rtt_ms=1000.0 * self.core.clock.rtt,
            snapshot_age_ms=scoring.p50_p99_ms([a - s for a, s in log.snapshot_times]),
            snapshot_gap_s=scoring.longest_gap([a for a, _ in log.snapshot_times]),
            velocities=self.velocities,
            codec=cfg.codec,
            update_bytes=0 if pub is None else pub.update_bytes,
            poses_sent=0 if pub is None else pub.poses_sent,
            frames_late=self.frames_late,
            asked_hz=cfg.rate,
            granted_hz=conn.session.rate or cfg.rate,  # an auto rate's last choice
            auto_rate=cfg.auto_rate,
            send_hz=cfg.send_rate,
            ending=ending,
            stale_s=log.stale_s,
            late_delay_ms=log.late_delay_ms(),
            ownership=self.ownership,
            role=None if self.actor is None else self.actor.role,
            resumed=len(self.policy.resumed_at),
            rejoined=len(self.policy.rejoined_at),
            relay=cfg.relays[self.policy.relay],
            streams=log.streams,
            render_log=log.render_log,
        )


async def run_bot(cfg: BotConfig, clock: Callable[[], float] = time.monotonic) -> BotReport:
    """Run one bot to the end of its duration and return what it measured."""
    return await Bot(cfg, clock).run()
