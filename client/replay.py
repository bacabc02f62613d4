"""Live replay: one bot per recorded user re-publishes a recording into a live server.

:func:`replay_live` reads a session file, connects one replay bot per recorded
user, joins each to the room (the recorded one unless ``room`` is given) with
the user's recorded stream names, label and rate, and publishes the user's
recorded pose updates with the original timing scaled by ``speed``, so live
bots and viewers see the session as it happened (``speed`` times faster).

Timing. With ``origin`` the first recorded arrival and ``S0`` the server time
at which the replay starts (the bots sync their clock with the server first):

- an update recorded as arriving at ``a`` is sent at server time
  ``S0 + (a - origin) / speed``;
- its capture times ``c`` are re-based and scaled: ``S0 + (c - origin) / speed``;
- poses are sent as recorded (float32, bit for bit);
- a user who joined (left) during the recording joins (leaves) at its scaled time.

A bot never sends more than ``max_send_rate`` updates a second (a token bucket
holding a quarter second's worth; the server drops updates beyond its own
per-connection limit, 120/s by default): when updates fall due faster (a high
``speed``, or a bot that fell behind) the due ones are merged into one update
carrying the newest keyframe of each stream -- what the server's latest-wins
relay would have kept anyway. ``speed="max"`` replays as fast as that limit
allows: 90 % of ``max_send_rate`` over the busiest user's mean update rate.

Velocities: a user whose every recorded update carried velocities (the
velocity variant) is replayed with them (joined with ``sends_velocities``),
scaled by ``speed`` along with the time line, so velocity subscribers get
them as recorded (as float16, bit for bit at speed 1).

Motion labels are re-based too (``t0`` shifted to the replay) when ``speed`` is
1, so live bots can score the replayed motion against its ground truth; at
other speeds the label becomes ``replay:<label>`` (not a ground truth).
Recorded events (grab, button, ...) are not replayed.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from websockets.exceptions import ConnectionClosed

from client.connection import ClientConnection
from protocol import (
    MAX_TEXT_LENGTH,
    Ping,
    Pong,
    PoseUpdate,
    Welcome,
    encode_update,
    is_valid_stream_name,
)
from recorder.export import read_session
from recorder.reader import StreamData, UserInfo
from recorder.replay import user_matches
from scenarios.motion import MotionSpec
from scenarios.receiver import ClockEstimator
from scenarios.traces import TraceError

__all__ = [
    "DEFAULT_MAX_SEND_RATE",
    "ReplayPlan",
    "UserPlan",
    "plan_replay",
    "replay_live",
    "select_plan",
]

F64 = NDArray[np.float64]
Clock = Callable[[], float]

#: Updates a second one replay bot sends at most (the server's default limit is 120).
DEFAULT_MAX_SEND_RATE = 100.0
_SYNC_PINGS = 8


@dataclass
class UserPlan:
    """One recorded user's updates, in arrival order.

    ``updates[i]`` is ``(recorded stream ids (n,), capture times (n,), poses (n, 7)
    float32)``, arriving at ``arrival[i]`` (recorded server clock).
    """

    user: int
    name: str
    label: str | None
    rate: float | None
    streams: dict[int, str]
    """Recorded stream id -> the name the bot joins with."""
    arrival: F64
    updates: list[tuple[NDArray[np.uint16], F64, NDArray[np.float32]]]
    joined: float | None = None
    left: float | None = None
    #: ``(n, 6)`` float32 velocities of each update (parallel to ``updates``) when
    #: every recorded update of the user carried them, else None.
    velocities: list[NDArray[np.float32]] | None = None

    @property
    def update_rate(self) -> float:
        """Mean recorded updates per second."""
        span = float(self.arrival[-1] - self.arrival[0]) if self.arrival.size > 1 else 0.0
        return (self.arrival.size - 1) / span if span > 0 else 0.0


@dataclass
class ReplayPlan:
    """What a replay publishes: the room, the time origin and every user's updates."""

    room: str
    origin: float
    end: float
    users: list[UserPlan] = field(default_factory=list)

    @property
    def updates(self) -> int:
        return sum(len(u.updates) for u in self.users)


def _stream_name(sid: int, name: str | None) -> str:
    return name if name is not None and is_valid_stream_name(name) else f"stream{sid}"


def _user_updates(
    streams: list[StreamData],
) -> tuple[
    F64,
    list[tuple[NDArray[np.uint16], F64, NDArray[np.float32]]],
    list[NDArray[np.float32]] | None,
]:
    """Regroup one user's per-stream keyframes into updates by arrival time.

    Keyframes recorded with the same arrival time came in one update (the
    server stamps each update on arrival); if a stream appears twice at one
    arrival time, its newest capture is kept. The third item holds each
    update's velocities if every keyframe of the user carried one.
    """
    sid = np.concatenate([np.full(len(s), s.stream, dtype=np.uint16) for s in streams])
    arr = np.concatenate([s.arrival for s in streams])
    cap = np.concatenate([s.times for s in streams])
    poses = np.concatenate([s.poses for s in streams])
    vel: NDArray[np.float32] | None = None
    if all(s.velocities is not None for s in streams):
        vel = np.concatenate([s.velocities for s in streams if s.velocities is not None])
        if np.isnan(vel).any():
            vel = None  # some updates carried none: replay the poses only
    order = np.lexsort((cap, sid, arr))
    sid, arr, cap, poses = sid[order], arr[order], cap[order], poses[order]
    if vel is not None:
        vel = vel[order]
    cuts = np.flatnonzero(np.diff(arr) != 0) + 1
    bounds = [0, *cuts.tolist(), arr.size]
    arrivals = []
    updates = []
    velocities: list[NDArray[np.float32]] | None = None if vel is None else []
    for lo, hi in itertools.pairwise(bounds):
        ids, caps, ps = sid[lo:hi], cap[lo:hi], poses[lo:hi]
        last = np.ones(ids.size, dtype=bool)
        last[:-1] = ids[1:] != ids[:-1]  # sorted by (sid, capture): keep the newest
        arrivals.append(float(arr[lo]))
        updates.append((ids[last], caps[last], ps[last]))
        if velocities is not None and vel is not None:
            velocities.append(vel[lo:hi][last])
    return np.asarray(arrivals, dtype=np.float64), updates, velocities


def plan_replay(path: str | os.PathLike[str], room: str | None = None) -> ReplayPlan:
    """Read a recording into per-user update lists (no network)."""
    data = read_session(path)
    by_user: dict[int, list[StreamData]] = {}
    for s in data.streams:
        by_user.setdefault(s.user, []).append(s)
    users: list[UserPlan] = []
    for user in sorted(by_user):
        info = data.users.get(user, UserInfo(user))
        arrival, updates, velocities = _user_updates(by_user[user])
        # Every stream the user joined with (those never published too), then any
        # published stream the presence records did not name.
        names = {sid: _stream_name(sid, n) for sid, n in info.streams.items()}
        for s in by_user[user]:
            names.setdefault(s.stream, _stream_name(s.stream, None))
        users.append(
            UserPlan(
                user=user,
                name=info.name or f"user{user}",
                label=info.label,
                rate=info.rate,
                streams=names,
                arrival=arrival,
                updates=updates,
                joined=info.joined,
                left=info.left,
                velocities=velocities,
            )
        )
    arrivals = [u.arrival for u in users if u.arrival.size]
    origin = float(min(a[0] for a in arrivals)) if arrivals else 0.0
    end = float(max(a[-1] for a in arrivals)) if arrivals else 0.0
    return ReplayPlan(room or data.session.get("room") or "replay", origin, end, users)


def _user_matches(up: UserPlan, wanted: str) -> bool:
    """``wanted`` names the user by id (``3`` or ``u3``) or by its recorded name."""
    return user_matches(up.user, up.name, wanted)


def select_plan(
    plan: ReplayPlan,
    start: float = 0.0,
    duration: float | None = None,
    users: Sequence[str] | None = None,
) -> ReplayPlan:
    """The part of ``plan`` a player was asked for (``replay --start --duration --users``).

    ``start`` and ``duration`` are seconds of the recording from its first
    arrival; the window keeps the updates arriving in ``[origin + start, origin +
    start + duration]`` and becomes the replay's time origin, so the replay begins
    at once. ``users`` keeps the users it names (id, ``u``-id or recorded name;
    ValueError for a name that matches nobody). Users left with no update go.
    """
    if start < 0 or (duration is not None and not duration > 0):
        raise ValueError("--start must be 0 or more and --duration positive")
    if users is not None:
        missing = [w for w in users if not any(_user_matches(up, w) for up in plan.users)]
        if missing:
            known = ", ".join(f"u{up.user} ({up.name})" for up in plan.users)
            raise ValueError(f"no recorded user {missing[0]!r}; the recording has {known}")
    lo = plan.origin + start
    hi = math.inf if duration is None else lo + duration
    if lo > plan.end:
        raise ValueError(
            f"--start {start:g} s is past the recording's end ({plan.end - plan.origin:.1f} s)"
        )
    kept: list[UserPlan] = []
    for up in plan.users:
        if users is not None and not any(_user_matches(up, w) for w in users):
            continue
        keep = np.flatnonzero((up.arrival >= lo) & (up.arrival <= hi))
        if keep.size == 0:
            continue
        vels = up.velocities
        kept.append(
            replace(
                up,
                arrival=up.arrival[keep],
                updates=[up.updates[i] for i in keep.tolist()],
                velocities=None if vels is None else [vels[i] for i in keep.tolist()],
                joined=up.joined if up.joined is not None and up.joined > lo else None,
                left=up.left if up.left is not None and up.left < hi else None,
            )
        )
    if not kept:
        raise ValueError("no pose updates in the chosen window and users")
    end = max(float(u.arrival[-1]) for u in kept)
    return ReplayPlan(plan.room, lo, end, kept)


def _replay_label(label: str | None, speed: float, shift: float) -> str | None:
    """The label a replay bot joins with (see the module docstring)."""
    if label is None:
        return None
    if speed == 1.0:
        try:
            spec = MotionSpec.parse(label)
            return MotionSpec(spec.source, spec.seed, spec.t0 + shift).label()
        except TraceError:
            pass
    return f"replay:{label}"[:MAX_TEXT_LENGTH]


class _ReplayBot:
    """One recorded user's bot: join, publish on schedule, drain what comes back."""

    def __init__(self, plan: UserPlan, conn: ClientConnection) -> None:
        self.plan = plan
        self.conn = conn
        self.ids: dict[int, int] = {}
        self.sent = 0
        self.merged = 0
        self.poses = 0
        self.lateness: list[float] = []
        self.joined_at: float | None = None
        #: Velocities are multiplied by this (the replay speed: time runs faster).
        self.velocity_scale = 1.0
        #: Set once every update has been sent.
        self.done = asyncio.Event()
        #: ``Join.codec``: compact (quantised in the server's volume) or raw records.
        self.codec = "compact"

    async def drain(self) -> None:
        with contextlib.suppress(ConnectionClosed):
            while True:
                await self.conn.recv()

    async def run(
        self,
        *,
        room: str,
        label: str | None,
        token: str | None,
        rate: float,
        to_local: Callable[[float], float],
        to_server: Callable[[float], float],
        scale: Callable[[float], float],
        send_rate: float,
        join_at: float,
        leave_at: float | None,
        finished: asyncio.Event,
        clock: Clock,
    ) -> None:
        plan, conn = self.plan, self.conn
        await asyncio.sleep(max(0.0, to_local(join_at) - clock()))
        names = tuple(plan.streams[sid] for sid in sorted(plan.streams))
        joined = await conn.join(
            room=room,
            streams=names,
            rate=rate,
            token=token,
            label=label,
            sends_velocities=plan.velocities is not None,
            codec=self.codec,
        )
        self.joined_at = to_server(clock())
        self.ids = {sid: joined.streams[plan.streams[sid]] for sid in plan.streams}
        async with asyncio.TaskGroup() as tg:
            drain = tg.create_task(self.drain())
            await self._publish(to_local, scale, send_rate, clock)
            self.done.set()
            if leave_at is not None:
                await asyncio.sleep(max(0.0, to_local(leave_at) - clock()))
            else:
                await finished.wait()
            with contextlib.suppress(ConnectionClosed):
                await conn.close("replay done")
            drain.cancel()

    async def _publish(
        self,
        to_local: Callable[[float], float],
        scale: Callable[[float], float],
        send_rate: float,
        clock: Clock,
    ) -> None:
        plan = self.plan
        due = [to_local(scale(a)) for a in plan.arrival.tolist()]
        n = len(due)
        i = 0
        seq = 0
        # Token bucket: ``max_send_rate`` a second, bursts of a quarter second's worth
        # (recorded arrivals jitter); the server's own bucket is larger.
        capacity = max(1.0, 0.25 * send_rate)
        tokens = capacity
        refilled = clock()
        while i < n:
            wait = due[i] - clock()
            if wait > 0:
                await asyncio.sleep(wait)
            now = clock()
            tokens = min(capacity, tokens + (now - refilled) * send_rate)
            refilled = now
            if tokens < 1.0:
                await asyncio.sleep((1.0 - tokens) / send_rate)
                now = clock()
                tokens = min(capacity, tokens + (now - refilled) * send_rate)
                refilled = now
            tokens -= 1.0
            now = clock()
            j = i + 1
            while j < n and due[j] <= now:
                j += 1
            vels = plan.velocities
            if j - i == 1:
                ids, caps, poses = plan.updates[i]
                vel = None if vels is None else vels[i]
            else:  # merge the due updates: newest keyframe of each stream
                ids, caps, poses, vel = _merge(
                    plan.updates[i:j], None if vels is None else vels[i:j]
                )
                self.merged += j - i - 1
            new_caps = np.array([scale(c) for c in caps.tolist()], dtype=np.float64)
            new_ids = np.array([self.ids[int(s)] for s in ids.tolist()], dtype=np.uint16)
            seq += 1
            if vel is not None and self.velocity_scale != 1.0:
                vel = vel * np.float32(self.velocity_scale)
            if self.codec == "raw":
                data = encode_update(
                    seq,
                    new_ids,
                    new_caps,
                    poses,
                    base_time=float(new_caps.max()),
                    velocities=vel,
                )
                await self.conn.send_bytes(data)
            else:  # the session codes it (compact frames keep per-stream baselines)
                update = PoseUpdate.from_arrays(
                    seq, new_ids, new_caps, poses, base_time=float(new_caps.max()), velocities=vel
                )
                await self.conn.send(update)
            self.lateness.append(now - due[j - 1])
            self.sent += 1
            self.poses += int(ids.size)
            i = j


def _merge(
    updates: list[tuple[NDArray[np.uint16], F64, NDArray[np.float32]]],
    velocities: list[NDArray[np.float32]] | None = None,
) -> tuple[NDArray[np.uint16], F64, NDArray[np.float32], NDArray[np.float32] | None]:
    """The newest keyframe of each stream (and its velocity, if given)."""
    newest: dict[int, tuple[float, NDArray[np.float32], NDArray[np.float32] | None]] = {}
    for u, (ids, caps, poses) in enumerate(updates):
        for k, sid in enumerate(ids.tolist()):
            c = float(caps[k])
            if sid not in newest or c > newest[sid][0]:
                v = None if velocities is None else velocities[u][k]
                newest[sid] = (c, poses[k], v)
    keys = sorted(newest)
    vel = None
    if velocities is not None:
        vel = np.stack([v for k in keys if (v := newest[k][2]) is not None]).astype(np.float32)
    return (
        np.array(keys, dtype=np.uint16),
        np.array([newest[k][0] for k in keys], dtype=np.float64),
        np.stack([newest[k][1] for k in keys]).astype(np.float32),
        vel,
    )


async def _sync_clock(conn: ClientConnection, est: ClockEstimator, n: int, clock: Clock) -> None:
    for seq in range(1, n + 1):
        await conn.send(Ping(seq=seq, time=clock()))
        while True:
            rec = await conn.recv()
            if isinstance(rec.event, Pong):
                est.add(rec.event.offset(rec.arrival), rec.event.round_trip(rec.arrival))
                break


def _percentiles_ms(values: list[float]) -> dict[str, float]:
    if not values:
        return {"p50": math.nan, "p95": math.nan, "max": math.nan}
    a = 1000.0 * np.asarray(values)
    return {
        "p50": float(np.percentile(a, 50)),
        "p95": float(np.percentile(a, 95)),
        "max": float(a.max()),
    }


def _replay_factor(plan: ReplayPlan, speed: float | Literal["max"], max_send_rate: float) -> float:
    """The time compression factor of ``speed`` (see :func:`replay_live`)."""
    if speed == "max":
        busiest = max(u.update_rate for u in plan.users)
        # 10 % headroom: recorded arrivals jitter around their mean rate.
        return 0.9 * max_send_rate / busiest if busiest > 0 else 1.0
    if isinstance(speed, int | float) and speed > 0 and math.isfinite(speed):
        return float(speed)
    raise ValueError(f"speed must be a positive number or 'max', got {speed!r}")


async def _connect_bots(
    plan: ReplayPlan,
    url: str,
    agent: str,
    factor: float,
    est: ClockEstimator,
    bots: list[_ReplayBot],
    clock: Clock,
) -> None:
    """Connect one bot per user (appended to ``bots`` as they connect); sync ``est``."""
    for k, up in enumerate(plan.users):
        conn = await ClientConnection.connect(url, agent=f"{agent}:{up.name}", clock=clock)
        bots.append(_ReplayBot(up, conn))
        bots[-1].velocity_scale = factor
        if k == 0:  # one process, one clock: one offset serves every bot
            await _sync_clock(conn, est, _SYNC_PINGS, clock)


async def _run_bots(
    plan: ReplayPlan,
    bots: list[_ReplayBot],
    welcome: Welcome,
    *,
    offset: float,
    start: float,
    factor: float,
    token: str | None,
    send_rate: float,
    linger: float,
    clock: Clock,
) -> None:
    """Run every bot to the end of the replay (``start`` on the server clock)."""

    def to_server(local: float) -> float:
        return local + offset

    def to_local(server: float) -> float:
        return server - offset

    def scale(t: float) -> float:
        return start + (t - plan.origin) / factor

    finished = asyncio.Event()
    async with asyncio.TaskGroup() as tg:
        for b in bots:
            up = b.plan
            rate = min(max(up.rate or welcome.min_rate, welcome.min_rate), welcome.max_rate)
            late = up.joined is not None and up.joined > plan.origin
            tg.create_task(
                b.run(
                    room=plan.room,
                    label=_replay_label(up.label, factor, start - plan.origin),
                    token=token,
                    rate=rate,
                    to_local=to_local,
                    to_server=to_server,
                    scale=scale,
                    send_rate=send_rate,
                    join_at=scale(up.joined) if late and up.joined is not None else -math.inf,
                    leave_at=None if up.left is None else scale(up.left),
                    finished=finished,
                    clock=clock,
                )
            )
        for b in bots:
            await b.done.wait()
        await asyncio.sleep(linger)
        finished.set()


def _report(
    path: str | os.PathLike[str],
    url: str,
    plan: ReplayPlan,
    speed: float | Literal["max"],
    factor: float,
    start: float,
    bots: list[_ReplayBot],
    est: ClockEstimator,
) -> dict[str, Any]:
    """:func:`replay_live`'s report (see there)."""
    lateness = [x for b in bots for x in b.lateness]
    return {
        "path": str(Path(path)),
        "url": url,
        "room": plan.room,
        "speed": factor,
        "speed_requested": speed,
        "origin": plan.origin,
        "server_start": start,
        "duration_s": (plan.end - plan.origin) / factor,
        "users": len(plan.users),
        "updates_recorded": plan.updates,
        "updates_sent": sum(b.sent for b in bots),
        "updates_merged": sum(b.merged for b in bots),
        "poses_sent": sum(b.poses for b in bots),
        "lateness_ms": _percentiles_ms(lateness),
        "clock_rtt_ms": 1000.0 * est.rtt,
        "streams": [
            {
                "recorded_user": b.plan.user,
                "recorded_stream": sid,
                "name": b.plan.streams[sid],
                "user": b.conn.user,
                "stream": b.ids.get(sid),
            }
            for b in bots
            for sid in sorted(b.plan.streams)
        ],
        "bots": [
            {
                "recorded_user": b.plan.user,
                "user": b.conn.user,
                "name": b.plan.name,
                "updates_sent": b.sent,
                "joined_at": b.joined_at,
                "velocities": b.plan.velocities is not None,
            }
            for b in bots
        ],
    }


async def replay_live(
    path: str | os.PathLike[str],
    url: str,
    speed: float | Literal["max"] = 1.0,
    room: str | None = None,
    *,
    token: str | None = None,
    max_send_rate: float = DEFAULT_MAX_SEND_RATE,
    lead: float = 0.5,
    linger: float = 0.5,
    agent: str = "posecast-replay",
    clock: Clock = time.monotonic,
    start_s: float = 0.0,
    duration_s: float | None = None,
    users: Sequence[str] | None = None,
    codec: str = "compact",
) -> dict[str, Any]:
    """Replay the recording at ``path`` into the server at ``url``; returns a report.

    ``speed``: a positive factor (1 = as recorded, 10 = ten times faster) or
    ``"max"``. ``room`` overrides the recorded room; ``token`` is passed to every
    join. The replay starts ``lead`` seconds after every bot present at the
    start has joined; bots that never left in the recording close ``linger``
    seconds after the last update. The report::

        {"path", "url", "room", "speed", "origin", "server_start", "duration_s",
         "users", "updates_recorded", "updates_sent", "updates_merged", "poses_sent",
         "lateness_ms": {"p50", "p95", "max"}, "clock_rtt_ms",
         "streams": [{"recorded_user", "recorded_stream", "name", "user", "stream"}],
         "bots": [{"recorded_user", "user", "name", "updates_sent", "joined_at",
                   "velocities"}]}

    A recorded update arriving at ``a`` (capture ``c``) is sent at server time
    ``server_start + (a - origin) / speed`` with capture ``server_start + (c -
    origin) / speed``.

    ``start_s``, ``duration_s`` and ``users`` replay only that window and those
    users (:func:`select_plan`); ``origin`` is then the window's start. ``codec``
    is each bot's ``Join.codec``: ``compact`` (poses quantised in the server's
    volume, to 0.25 mm and 0.034 deg) or ``raw`` (the recorded floats exactly).
    """
    if not max_send_rate > 0:
        raise ValueError("max_send_rate must be positive")
    # Reading the recording is file I/O: not on the event loop.
    plan = await asyncio.to_thread(plan_replay, path, room)
    if start_s or duration_s is not None or users is not None:
        plan = select_plan(plan, start_s, duration_s, users)
    if not plan.users:
        raise ValueError(f"{path}: no pose updates to replay")
    factor = _replay_factor(plan, speed, max_send_rate)
    est = ClockEstimator()
    bots: list[_ReplayBot] = []
    start = math.nan
    try:
        await _connect_bots(plan, url, agent, factor, est, bots, clock)
        for b in bots:
            b.codec = codec
        welcome = bots[0].conn.welcome
        assert welcome is not None
        offset = est.offset
        # The replay's server-clock start: ``lead`` leaves the bots present at the
        # start time to join (their labels, re-based to it, go with the join).
        start = clock() + offset + lead
        await _run_bots(
            plan,
            bots,
            welcome,
            offset=offset,
            start=start,
            factor=factor,
            token=token,
            send_rate=max_send_rate,
            linger=linger,
            clock=clock,
        )
    finally:
        for b in bots:
            with contextlib.suppress(Exception):
                await b.conn.close("replay done")
    return _report(path, url, plan, speed, factor, start, bots, est)
