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
timers: a request must not overtake the release it followed). An owner's bot
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
import collections
import contextlib
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from websockets.exceptions import ConnectionClosed

from posecast.client.connection import ClientConnection, JoinRefused
from posecast.client.core import ClientCore
from posecast.client.playout import ClockEstimator
from posecast.client.publish import send_update
from posecast.client.receiver import Receiver
from posecast.client.reconnect import Reconnect
from posecast.protocol import (
    MAX_TEXT_LENGTH,
    ErrorMessage,
    ObjectCreate,
    ObjectInfo,
    Owner,
    Release,
    RequestOwnership,
    Welcome,
)
from posecast.protocol.errors import ErrorCode
from posecast.protocol.objects import pose_tuple
from posecast.recorder.objects import ObjectAction
from posecast.recorder.plan import (
    ReplayPlan,
    UserPlan,
    merge_updates,
    plan_replay,
    select_plan,
    spawn_plan,
)
from posecast.scenarios.motion import MotionSpec
from posecast.scenarios.traces import TraceError

__all__ = [
    "DEFAULT_MAX_SEND_RATE",
    "DEFAULT_OBJECT_PATIENCE",
    "ReplayPlan",
    "UserPlan",
    "plan_replay",
    "replay_live",
    "select_plan",
]

F64 = NDArray[np.float64]
#: A held-back object keyframe: capture (server clock), pose row, velocity row.
_Held = tuple[float, NDArray[np.float32], NDArray[Any] | None]
Clock = Callable[[], float]
Vec3 = tuple[float, float, float]

#: Updates a second one replay bot sends at most (the server's default limit is 120).
DEFAULT_MAX_SEND_RATE = 100.0
#: Seconds a bot waits for a live object to be in its recorded state before an action.
DEFAULT_OBJECT_PATIENCE = 1.0
#: Keyframes of one object a bot holds back while it waits for the object's grant.
BACKLOG = 32
_SYNC_PINGS = 8
#: What a replay bot's core is set up with: it renders nothing, so any method and
#: rate serve (a plan without a recorded rate asks for this one).
_METHODS = ("soa",)
_RATE = 10.0


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


class _ReplayBot:
    """One recorded user's bot: join, publish on schedule, take in what comes back.

    An adapter over the client core, as the bot is: its :class:`client.receiver.Receiver`
    syncs the clock and hands every event to a :class:`client.core.ClientCore` (the
    room as a receiver keeps it), and tells this bot of the objects' owners; it never
    reconnects (a replay that lost its relay is over). Updates go out through
    :func:`client.publish.send_update`, as the bot's."""

    def __init__(self, plan: UserPlan, conn: ClientConnection, url: str, clock: Clock) -> None:
        self.plan = plan
        self.conn = conn
        self.core = ClientCore(_METHODS, plan.rate or _RATE)
        self.receiver = Receiver(self.core, Reconnect((url,), enabled=False), clock)
        self.receiver.attach(conn)
        self.receiver.listen(self._heard)
        self.ids: dict[int, int] = {}
        self.sent = 0
        self.merged = 0
        self.poses = 0
        self.lateness: list[float] = []
        self.joined_at: float | None = None
        #: Velocities are multiplied by this (the replay speed: time runs faster).
        self.velocity_scale = 1.0
        #: Set once every update has been sent, and once it has joined.
        self.done, self.joined = asyncio.Event(), asyncio.Event()
        #: ``Join.codec``: compact (quantised in the server's volume) or raw records.
        self.codec = "compact"
        #: Recorded user id -> live user id of every bot of the replay (shared).
        self.users: dict[int, int] = {}
        #: Live object stream -> its live owner, as this bot was told.
        self.owners: dict[int, int | None] = {}
        self.patience = DEFAULT_OBJECT_PATIENCE
        self.actions_sent = 0
        #: Actions sent before the live object reached its recorded state.
        self.impatient = 0
        self.refused: list[str] = []
        #: Live object streams this bot asked for and has no answer about yet.
        self.pending: set[int] = set()
        #: Objects this bot created to hold and has not heard of yet (by name).
        self.creating: set[str] = set()
        #: Recorded object stream -> its keyframes held back until the grant arrives.
        self.backlog: dict[int, collections.deque[_Held]] = {}
        #: Held-back keyframes sent once the grant came, and ones given up.
        self.keyframes_late = 0
        self.keyframes_dropped = 0
        self._changed = asyncio.Event()

    def _heard(self, ev: object, arrival: float, size: int) -> None:
        """An event the core took in: the objects' owners and refusals are this bot's."""
        if isinstance(ev, ObjectInfo | Owner):
            self.owners[ev.stream] = ev.owner
            self.pending.discard(ev.stream)
            if isinstance(ev, ObjectInfo):
                self.creating.discard(ev.name)
        elif isinstance(ev, ErrorMessage) and ev.code == ErrorCode.OWNERSHIP_REFUSED:
            self.refused.append(ev.message)
            self.pending.clear()  # errors do not say which request
            self.creating.clear()
        else:
            return
        self._changed.set()

    async def _wait_for(self, ready: Callable[[], bool], clock: Clock) -> bool:
        """Wait until ``ready()`` (the live room caught up), at most ``patience`` s."""
        deadline = clock() + self.patience
        while not ready():
            left = deadline - clock()
            if left <= 0:
                return False
            self._changed.clear()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._changed.wait(), left)
        return True

    async def _act(self, act: ObjectAction, clock: Clock) -> None:
        """Send one recorded object action once the live object is in its recorded state."""
        objects = self.conn.session.objects
        if act.kind == "create" and act.name not in objects:
            assert act.pose is not None
            pose = pose_tuple("object_create.pose", act.pose)
            create = ObjectCreate(act.name, pose, act.keep, act.steal, act.hold)
            if act.hold:
                self.creating.add(act.name)
            await self.conn.send(create)
            self.actions_sent += 1
            if act.hold:  # held before the keyframes that follow are sent
                held = self.conn.session.held
                await self._wait_for(lambda: objects.get(act.name, -1) in held, clock)
            return
        # Another bot creates it: wait for it, then for the owner it had before.
        known = act.previous is None or act.previous in self.users  # replayed users only
        before = None if act.previous is None else self.users.get(act.previous)
        ok = await self._wait_for(
            lambda: (
                act.name in objects
                and (not known or self.owners.get(objects[act.name], -1) == before)
            ),
            clock,
        )
        self.impatient += not ok
        stream = objects.get(act.name)
        if stream is None:
            return  # never created here: nothing to ask for
        if act.kind == "release":
            scale = self.velocity_scale

            def scaled(v: Vec3 | None) -> Vec3 | None:
                return None if v is None else (scale * v[0], scale * v[1], scale * v[2])

            message: Release | RequestOwnership = Release(
                stream, scaled(act.velocity), scaled(act.angular)
            )
        else:
            message = RequestOwnership(stream, steal=act.steal, lock=act.lock)
            self.pending.add(stream)
        await self.conn.send(message)
        self.actions_sent += 1
        # The answer before the keyframes it allows (at most ``patience`` again).
        await self._wait_for(lambda: stream not in self.pending, clock)

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
        self.joined.set()
        self.ids = {sid: joined.streams[plan.streams[sid]] for sid in plan.streams}
        async with asyncio.TaskGroup() as tg:
            drain = tg.create_task(self.receiver.receive(conn))
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
        n, i, seq = len(due), 0, 0
        actions, k = plan.actions, 0
        # Token bucket: ``max_send_rate`` a second, bursts of a quarter second's worth
        # (recorded arrivals jitter); the server's own bucket is larger.
        capacity = max(1.0, 0.25 * send_rate)
        tokens = capacity
        refilled = clock()

        def action_first(at: int) -> bool:
            """The next action comes before update ``at`` (see ObjectAction.grant)."""
            if k >= len(actions):
                return False
            a, t = actions[k], float(plan.arrival[at]) if at < n else math.inf
            return a.time < t or (a.time == t and a.grant)

        while i < n or k < len(actions):
            if action_first(i):
                wait = to_local(scale(actions[k].time)) - clock()
                if wait > 0:
                    await asyncio.sleep(wait)
                await self._act(actions[k], clock)
                seq += await self.send_backlog(seq + 1)
                k += 1
                continue
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
            while j < n and due[j] <= now and not action_first(j):
                j += 1
            sent = await self._send_update(seq + 1, i, j, scale)
            seq += sent
            self.lateness.append(now - due[j - 1])
            i = j
        if self.backlog:  # the last keyframes wait for their grant, once more at most
            await self._wait_for(lambda: not any(map(self._awaiting, self._backlogged())), clock)
            await self.send_backlog(seq + 1)
            self.keyframes_dropped += sum(map(len, self.backlog.values()))
            self.backlog.clear()

    async def _send_update(self, seq: int, i: int, j: int, scale: Callable[[float], float]) -> int:
        """Send recorded updates ``i:j`` as one (merged if more), after the held-back
        keyframes whose grant came; the number of updates sent (seq ``seq`` on)."""
        plan, vels = self.plan, self.plan.velocities
        if j - i == 1:
            ids, caps, poses = plan.updates[i]
            vel = None if vels is None else vels[i]
        else:  # merge the due updates: newest keyframe of each stream
            ids, caps, poses, vel = merge_updates(
                plan.updates[i:j], None if vels is None else vels[i:j]
            )
            self.merged += j - i - 1
        sent = await self.send_backlog(seq)
        new_caps = np.array([scale(c) for c in caps.tolist()], dtype=np.float64)
        keep = self._live_ids(ids)
        for k in np.flatnonzero(~keep).tolist():
            self._hold_back(int(ids[k]), (new_caps[k], poses[k], None if vel is None else vel[k]))
        if not keep.any():
            return sent  # only objects this bot does not hold (live) right now
        live = np.array([self._live_id(int(s)) for s in ids[keep].tolist()], dtype=np.uint16)
        await self._send(
            seq + sent, live, new_caps[keep], poses[keep], vel[keep] if vel is not None else None
        )
        self.sent += 1
        return sent + 1

    async def _send(
        self,
        seq: int,
        live: NDArray[np.uint16],
        caps: F64,
        poses: NDArray[Any],
        vel: NDArray[Any] | None,
    ) -> None:
        if vel is not None and self.velocity_scale != 1.0:
            vel = vel * np.float32(self.velocity_scale)
        await send_update(self.conn, self.codec, seq, live, caps, poses, vel)
        self.poses += int(live.size)

    def _hold_back(self, sid: int, keyframe: _Held) -> None:
        """Keep an object's keyframe for its grant if this bot awaits one (else drop it:
        the relay would not take it)."""
        if not self._awaiting(self.plan.objects[sid]):
            return
        held = self.backlog.setdefault(sid, collections.deque())
        if len(held) >= BACKLOG:
            held.popleft()
            self.keyframes_dropped += 1
        held.append(keyframe)

    def _backlogged(self) -> list[str]:
        """Names of the objects with held-back keyframes."""
        return [self.plan.objects[sid] for sid in self.backlog]

    def _awaiting(self, name: str) -> bool:
        """This bot asked for object ``name`` (a request, or a create that holds it)
        and the relay's answer has not reached it yet."""
        stream = self.conn.session.objects.get(name)
        return name in self.creating if stream is None else stream in self.pending

    async def send_backlog(self, seq: int) -> int:
        """Send the held-back keyframes of every object granted since, one update each
        (seq ``seq`` on); drop those of objects no longer awaited. Updates sent."""
        sent = 0
        objects, held = self.conn.session.objects, self.conn.session.held
        for sid in list(self.backlog):
            name = self.plan.objects[sid]
            stream = objects.get(name)
            if stream is not None and stream in held:
                live = np.array([stream], dtype=np.uint16)
                for cap, pose, vel in self.backlog.pop(sid):
                    v = None if vel is None else vel[None]
                    await self._send(seq + sent, live, np.array([cap]), pose[None], v)
                    sent += 1
                    self.keyframes_late += 1
            elif not self._awaiting(name):
                self.keyframes_dropped += len(self.backlog.pop(sid))
        return sent

    def _live_id(self, sid: int) -> int:
        name = self.plan.objects.get(sid)
        return self.ids[sid] if name is None else self.conn.session.objects[name]

    def _live_ids(self, ids: NDArray[np.uint16]) -> NDArray[np.bool_]:
        """Which recorded streams of an update this bot may send now (objects: held)."""
        if not self.plan.objects:
            return np.ones(ids.size, dtype=bool)
        objects, held = self.conn.session.objects, self.conn.session.held
        return np.array(
            [
                s not in self.plan.objects or objects.get(self.plan.objects[s], -1) in held
                for s in ids.tolist()
            ],
            dtype=bool,
        )


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
    bots: list[_ReplayBot],
    clock: Clock,
) -> None:
    """Connect one bot per user (appended to ``bots`` as they connect); the first syncs
    its core's clock estimate (one process, one clock: its offset serves every bot).

    ``settings``: the speed factor, the codec and the object patience of every bot."""
    factor, codec, patience = settings
    for k, up in enumerate(plan.users):
        conn = await ClientConnection.connect(url, agent=f"{agent}:{up.name}", clock=clock)
        bots.append(_ReplayBot(up, conn, url, clock))
        bots[-1].velocity_scale = factor
        bots[-1].codec, bots[-1].patience = codec, patience
        if k == 0:
            await bots[-1].receiver.sync(conn, _SYNC_PINGS)
    users = {b.plan.user: b.conn.user for b in bots}
    for b in bots:
        b.users = users


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
    bots: list[_ReplayBot],
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
) -> tuple[float, list[_ReplayBot]]:
    """Connect the bots, open the room (:func:`_open_room`), run the replay; its start
    (server clock) and the bots. ``timing``: lead, linger and the send rate."""
    lead, linger, send_rate = timing
    bots: list[_ReplayBot] = []
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
