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

Shared objects (``recorder.objects``) are replayed as the handovers that moved
them: the creator's bot creates each object at its scaled create time, and the
bots request and release it at the scaled times of the recorded ownership
changes (steal and lock as recorded; a throw with the recorded velocities times
``speed``), so the live relay decides the same changes and flies thrown objects
itself; the relay's recorded flight keyframes are not sent. Before each request
or release a bot waits, up to ``object_patience`` seconds, until the live object
has the owner it had before the recorded change (the bots run on their own
timers: a request must not overtake the release it followed), and before a
steal, until its snapshots show the victim's last keyframe of the object
recorded before the steal (nor may a steal overtake those). An owner's bot
sends the object's recorded keyframes in its updates while the live relay says
it holds the object (entries it does not hold are left out; after a request it
waits, as long again at most, for the answer before it sends on). While the
relay's answer to its request (or create) has not reached it, the bot holds
the object's keyframes back, at most ``BACKLOG`` of them (a burst the relay's
update bucket of a second's worth takes), and sends each in an update of its
own once the grant arrives, before its next scheduled update (or right after the
answer, or at its end, after waiting for the answer once more): late,
as a bot behind its schedule sends, but none lost (the report's ``objects``
count them: ``keyframes_late``, and ``keyframes_dropped`` when the answer was a
refusal or the backlog overflowed). A recorded
``owner-left`` happens when its bot leaves; objects are found by name, so a
replay into a room that still has them (``--loop``) uses them as they are.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import os
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
from websockets.exceptions import ConnectionClosed

from posecast.client.connection import ClientConnection, JoinRefused
from posecast.client.playout import ClockEstimator
from posecast.client.replaybot import BACKLOG, DEFAULT_OBJECT_PATIENCE, Clock, ReplayBot
from posecast.protocol import MAX_TEXT_LENGTH, Welcome
from posecast.recorder.plan import ReplayPlan, UserPlan, plan_replay, select_plan, spawn_plan
from posecast.scenarios.motion import MotionSpec
from posecast.scenarios.traces import TraceError

__all__ = [
    "BACKLOG",
    "DEFAULT_MAX_SEND_RATE",
    "DEFAULT_OBJECT_PATIENCE",
    "ReplayPlan",
    "UserPlan",
    "plan_replay",
    "replay_live",
    "select_plan",
]

#: Updates a second one replay bot sends at most (the server's default limit is 120).
DEFAULT_MAX_SEND_RATE = 100.0
_SYNC_PINGS = 8


def _replay_label(label: str | None, speed: float, shift: float) -> str | None:
    """The label a replay bot joins with (see the module docstring)."""
    if label is None:
        return None
    if speed == 1.0:
        try:
            spec = MotionSpec.parse(label)
            return replace(spec, t0=spec.t0 + shift).label()
        except TraceError:
            pass
    return f"replay:{label}"[:MAX_TEXT_LENGTH]


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
    settings: tuple[float, str, float],
    bots: list[ReplayBot],
    clock: Clock,
) -> None:
    """Connect one bot per user (appended to ``bots`` as they connect); the first syncs
    its core's clock estimate (one process, one clock: its offset serves every bot).

    ``settings``: the speed factor, the codec and the object patience of every bot."""
    factor, codec, patience = settings
    for k, up in enumerate(plan.users):
        conn = await ClientConnection.connect(url, agent=f"{agent}:{up.name}", clock=clock)
        bots.append(ReplayBot(up, conn, url, clock))
        bots[-1].velocity_scale = factor
        bots[-1].codec, bots[-1].patience = codec, patience
        if k == 0:
            await bots[-1].receiver.sync(conn, _SYNC_PINGS)
    users = {b.plan.user: b.conn.user for b in bots}
    peers = {b.plan.user: b.plan for b in bots}
    for b in bots:
        b.users, b.peers = users, peers


async def _run_bots(
    plan: ReplayPlan,
    bots: list[ReplayBot],
    welcome: Welcome,
    *,
    offset: float,
    start: float,
    factor: float,
    token: str | None,
    send_rate: float,
    linger: float,
    clock: Clock,
    opener: ClientConnection | None = None,
) -> None:
    """Run every bot to the end of the replay (``start`` on the server clock); the
    ``opener`` (:func:`_open_room`) leaves once the bots present at the start joined."""

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
        if opener is not None:
            first = [b for b in bots if b.plan.joined is None or b.plan.joined <= plan.origin]
            for b in first:
                await b.joined.wait()
            with contextlib.suppress(ConnectionClosed):
                await opener.close("replay started")
        for b in bots:
            await b.done.wait()
        await asyncio.sleep(linger)
        finished.set()


async def _open_room(
    url: str, room: str, rate: float, agent: str, clock: Clock
) -> ClientConnection | None:
    """A spectator in ``room`` before the replay's clock starts: a relay that holds a
    room's first join while it opens the room's recording (a process starting: seconds
    on a loaded machine) does it now, not inside the bots' ``lead``, which would leave
    them joining late and their object actions, overdue, racing each other.
    Spectators are neither announced nor recorded. None if the relay refuses it (the
    bots then meet the same refusal)."""
    conn = await ClientConnection.connect(url, agent=f"{agent}:opener", clock=clock)
    try:
        await conn.join(room=room, streams=("head",), rate=rate, spectator=True)
    except JoinRefused:
        with contextlib.suppress(ConnectionClosed):
            await conn.close("refused")
        return None
    return conn


def _report(
    path: str | os.PathLike[str],
    url: str,
    plan: ReplayPlan,
    speed: float | Literal["max"],
    factor: float,
    start: float,
    bots: list[ReplayBot],
    est: ClockEstimator,
) -> dict[str, Any]:
    """:func:`replay_live`'s report (see there). ``objects.impatient`` counts object
    actions sent before the live object reached its recorded owner (after the
    bot's patience); ``objects.refused`` holds the relay's refusals;
    ``objects.keyframes_late`` counts object keyframes held back until their grant
    reached the bot and sent then, ``objects.keyframes_dropped`` those given up (a
    refusal, or more than ``BACKLOG`` waiting)."""
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
                "object_actions": b.actions_sent,
            }
            for b in bots
        ],
        "objects": {
            "actions_recorded": sum(len(b.plan.actions) for b in bots),
            "actions_sent": sum(b.actions_sent for b in bots),
            "impatient": sum(b.impatient for b in bots),
            "refused": [m for b in bots for m in b.refused],
            "keyframes_late": sum(b.keyframes_late for b in bots),
            "keyframes_dropped": sum(b.keyframes_dropped for b in bots),
        },
    }


def _plan(
    path: str | os.PathLike[str],
    room: str | None,
    window: tuple[float, float | None, Sequence[str] | None],
    spawn: str,
) -> ReplayPlan:
    """The recording's replay plan: read, cut to the ``(start, duration, users)``
    window, moved onto the ``spawn`` layout; a plan with no users is refused."""
    plan = plan_replay(path, room)
    start_s, duration_s, users = window
    if start_s or duration_s is not None or users is not None:
        plan = select_plan(plan, start_s, duration_s, users)
    plan = spawn_plan(plan, spawn)
    if not plan.users:
        raise ValueError(f"{path}: no pose updates to replay")
    return plan


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
    object_patience: float = DEFAULT_OBJECT_PATIENCE,
    spawn: str = "none",
) -> dict[str, Any]:
    """Replay the recording at ``path`` into the server at ``url``; returns a report.

    ``speed``: a positive factor (1 = as recorded, 10 = ten times faster) or
    ``"max"``. ``room`` overrides the recorded room; ``token`` is passed to every
    join. The replay starts ``lead`` seconds after a spectator joined its room (so a
    relay that opens the room's recording at its first join has done so; not with a
    ``token``): the bots present at the start join within that lead, the spectator
    leaves once they have. Bots that never left in the recording close ``linger``
    seconds after the last update. The report::

        {"path", "url", "room", "speed", "origin", "server_start", "duration_s",
         "users", "updates_recorded", "updates_sent", "updates_merged", "poses_sent",
         "lateness_ms": {"p50", "p95", "max"}, "clock_rtt_ms",
         "streams": [{"recorded_user", "recorded_stream", "name", "user", "stream"}],
         "bots": [{"recorded_user", "user", "name", "updates_sent", "joined_at",
                   "velocities", "object_actions"}],
         "objects": {"actions_recorded", "actions_sent", "impatient", "refused",
                     "keyframes_late", "keyframes_dropped"}}

    A recorded update arriving at ``a`` (capture ``c``) is sent at server time
    ``server_start + (a - origin) / speed`` with capture ``server_start + (c -
    origin) / speed``.

    ``start_s``, ``duration_s`` and ``users`` replay only that window and those
    users (:func:`select_plan`); ``origin`` is then the window's start. ``codec``
    is each bot's ``Join.codec``: ``compact`` (poses quantised in the server's
    volume, to 0.25 mm and 0.034 deg) or ``raw`` (the recorded floats exactly);
    ``object_patience``: see the module docstring (shared objects). ``spawn``: a
    layout of :mod:`scenarios.spawn` the users are moved onto
    (:func:`recorder.plan.spawn_plan`; ``none``: as recorded)."""
    if not max_send_rate > 0:
        raise ValueError("max_send_rate must be positive")
    # Reading the recording is file I/O: not on the event loop.
    plan = await asyncio.to_thread(_plan, path, room, (start_s, duration_s, users), spawn)
    factor = _replay_factor(plan, speed, max_send_rate)
    settings = (factor, codec, object_patience)
    start, bots = await _replay(
        plan, url, agent, settings, token, (lead, linger, max_send_rate), clock
    )
    return _report(path, url, plan, speed, factor, start, bots, bots[0].core.clock)


async def _replay(
    plan: ReplayPlan,
    url: str,
    agent: str,
    settings: tuple[float, str, float],
    token: str | None,
    timing: tuple[float, float, float],
    clock: Clock,
) -> tuple[float, list[ReplayBot]]:
    """Connect the bots, open the room (:func:`_open_room`), run the replay; its start
    (server clock) and the bots. ``timing``: lead, linger and the send rate."""
    lead, linger, send_rate = timing
    bots: list[ReplayBot] = []
    opener: ClientConnection | None = None
    try:
        await _connect_bots(plan, url, agent, settings, bots, clock)
        welcome = bots[0].conn.welcome
        assert welcome is not None
        offset = bots[0].core.clock.offset
        if token is None:  # (a token's user would be taken by the opener)
            opener = await _open_room(url, plan.room, welcome.min_rate, agent, clock)
        # The replay's server-clock start: ``lead`` leaves the bots present at the
        # start time to join (their labels, re-based to it, go with the join).
        start = clock() + offset + lead
        await _run_bots(
            plan,
            bots,
            welcome,
            offset=offset,
            start=start,
            factor=settings[0],
            token=token,
            send_rate=send_rate,
            linger=linger,
            clock=clock,
            opener=opener,
        )
    finally:
        for conn in [b.conn for b in bots] + ([] if opener is None else [opener]):
            with contextlib.suppress(Exception):
                await conn.close("replay done")
    return start, bots
