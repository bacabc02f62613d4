"""One replay bot: a recorded user's updates and object actions sent into a live relay.

:func:`client.replay.replay_live` runs one :class:`ReplayBot` per recorded user
(its module docstring has the timing rules a replay keeps). A bot joins, then
walks its user's plan (:class:`recorder.plan.UserPlan`): each update goes out at
its scaled time (the due ones merged into one past ``max_send_rate``), each
recorded object action (:class:`recorder.objects.ObjectAction`) before the
update it came before, once the live object has the owner it had then (at most
``patience`` s; a steal also waits until the relay shows the last keyframe of
the object its victim's bot sent before it, which the relay had taken before
the recorded steal: the bots run on their own timers). An object's keyframes go
in the owner's updates while the live relay says this bot holds the object;
while the relay's answer to its request (or create) has not reached the bot,
they wait in a backlog of at most :data:`BACKLOG` per object and go out once the
grant has come.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import math
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray
from websockets.exceptions import ConnectionClosed

from posecast.client.connection import ClientConnection
from posecast.client.core import ClientCore
from posecast.client.publish import send_update
from posecast.client.receiver import Receiver
from posecast.client.reconnect import Reconnect
from posecast.protocol import (
    ROOM_USER,
    ErrorMessage,
    ObjectCreate,
    ObjectInfo,
    Owner,
    Release,
    RequestOwnership,
    Snapshot,
)
from posecast.protocol.errors import ErrorCode
from posecast.protocol.objects import pose_tuple
from posecast.recorder.objects import ObjectAction
from posecast.recorder.plan import UserPlan, merge_updates

__all__ = ["BACKLOG", "DEFAULT_OBJECT_PATIENCE", "Clock", "ReplayBot"]

F64 = NDArray[np.float64]
#: A held-back object keyframe: capture (server clock), pose row, velocity row.
_Held = tuple[float, NDArray[np.float32], NDArray[Any] | None]
Clock = Callable[[], float]
Vec3 = tuple[float, float, float]

#: Seconds a bot waits for a live object to be in its recorded state before an action.
DEFAULT_OBJECT_PATIENCE = 1.0
#: Keyframes of one object a bot holds back while it waits for the object's grant.
BACKLOG = 32
#: What a replay bot's core is set up with: it renders nothing, so any method and
#: rate serve (a plan without a recorded rate asks for this one).
_METHODS = ("soa",)
_RATE = 10.0
#: How far below a capture a snapshot's may be and still be that keyframe (s).
_CAPTURE_SLACK = 0.001


class ReplayBot:
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
        #: Recorded user -> its plan, for every bot of the replay (shared).
        self.peers: dict[int, UserPlan] = {}
        #: Live object stream -> the newest capture of it this bot's snapshots showed.
        self.seen: dict[int, float] = {}
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
        elif not (isinstance(ev, Snapshot) and self.plan.actions and self._saw(ev)):
            return
        self._changed.set()

    def _saw(self, snapshot: Snapshot) -> bool:
        """Note the newest capture of each object in ``snapshot``; True if one is newer."""
        newer = False
        for k in np.flatnonzero(snapshot.users == ROOM_USER).tolist():
            stream, capture = int(snapshot.streams[k]), float(snapshot.capture_times[k])
            if capture > self.seen.get(stream, -math.inf):
                self.seen[stream] = capture
                newer = True
        return newer

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

    def handed_over(self, act: ObjectAction) -> float | None:
        """The recorded capture of the last keyframe of ``act``'s object that its previous
        owner sent before the change, when that owner is another bot of the replay (a
        steal): the relay took it before the change, so it must have it before the
        request goes (the bots run on their own timers). None if there is none."""
        previous = act.previous
        plan = None if previous in (None, self.plan.user) else self.peers.get(previous)
        if plan is None:
            return None
        sids = [sid for sid, name in plan.objects.items() if name == act.name]
        for i in range(int(np.searchsorted(plan.arrival, act.time, side="right")) - 1, -1, -1):
            ids, caps, _ = plan.updates[i]
            hit = np.flatnonzero(np.isin(ids, sids))
            if hit.size:
                return float(caps[hit[-1]])
        return None

    async def _act(self, act: ObjectAction, clock: Clock, scale: Callable[[float], float]) -> None:
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
        # Another bot creates it: wait for it, then for the owner it had before (and
        # for that owner's keyframes sent before the change, if it was another bot's).
        known = act.previous is None or act.previous in self.users  # replayed users only
        before = None if act.previous is None else self.users.get(act.previous)
        last = self.handed_over(act)
        # (compact captures come in 1 ms steps)
        due = -math.inf if last is None else scale(last) - _CAPTURE_SLACK
        ok = await self._wait_for(
            lambda: (
                act.name in objects
                and (not known or self.owners.get(objects[act.name], -1) == before)
                and self.seen.get(objects[act.name], -math.inf) >= due
            ),
            clock,
        )
        self.impatient += not ok
        stream = objects.get(act.name)
        if stream is None:
            return  # never created here: nothing to ask for
        if act.kind == "release":
            speed = self.velocity_scale

            def scaled(v: Vec3 | None) -> Vec3 | None:
                return None if v is None else (speed * v[0], speed * v[1], speed * v[2])

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
                await self._act(actions[k], clock, scale)
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
