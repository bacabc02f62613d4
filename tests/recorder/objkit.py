"""A recorded session with shared objects: two real clients on a real recording relay.

:func:`record_handover_session` starts the relay on loopback (port 0) with
``record_dir``, joins two real websocket clients (``a`` and ``b``, head only)
and plays a scripted scene with a stealable ``object:drill`` (created held by
a) and an ``object:cup`` of b's that dies with it (``keep=False``):

    a creates the drill held, moves it, throws it; b catches it mid-air, moves
    it, puts it down (release); a takes it (request), b steals it, moves it and
    throws it again; it lands; a takes it with a lock, moves it, and leaves
    holding it (owner-left); b leaves (its cup is removed).

Every client publishes its head at 30 Hz all along, and the drill in the same
updates while it holds it; b's captures run 100 ms behind (``SKEW_B``). Each
step waits for the relay's ``owner`` message, a hold lasts until the other
client has seen so many of the holder's drill keyframes, a catch comes after a
few flight keyframes, a pick-up after the relay has landed the drill (no
sleeps standing in for ordering or for time passing). What the clients saw is
returned beside
the recording, so tests compare the file against the session, not against
numbers written here.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np
from support import Pacer, poll_until, running_server
from websockets.exceptions import ConnectionClosed

from posecast.client.connection import ClientConnection
from posecast.protocol import (
    ROOM_USER,
    ObjectCreate,
    ObjectInfo,
    Owner,
    PoseUpdate,
    Release,
    Snapshot,
)
from posecast.protocol.objects import RequestOwnership
from posecast.server.app import ServerConfig
from posecast.server.room import Room

__all__ = ["ROOM", "Actor", "Session", "drill_pose", "record_handover_session"]

ROOM = "objects"
RATE = 30.0
DRILL = (0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0)
CUP = (1.0, 0.5, 0.0, 1.0, 0.0, 0.0, 0.0)
#: b stamps its captures this far behind the server clock (more than a tick): the
#: relay shifts its first keyframe after each grant to 1 ms after the drill's newest.
SKEW_B = -0.1


def drill_pose(t: float, x0: float, y0: float) -> tuple[float, ...]:
    """A held drill: moving along +x at 0.5 m/s and turning about y at 1 rad/s."""
    return (
        x0 + 0.5 * t,
        y0 + 0.1 * math.sin(3.0 * t),
        0.2,
        math.cos(t / 2),
        0.0,
        math.sin(t / 2),
        0.0,
    )


@dataclass
class Actor:
    """One joined client: publishes head (and the drill while holding), keeps what it gets."""

    conn: ClientConnection
    #: Added to the captures it stamps (a client whose clock estimate is off).
    skew: float = 0.0
    owners: list[Owner] = field(default_factory=list)
    infos: list[ObjectInfo] = field(default_factory=list)
    #: The drill's newest keyframe seen in snapshots (capture time, pose).
    drill_seen: tuple[float, tuple[float, ...]] | None = None
    drill: int | None = None
    #: While set: (hold start on the server clock, x0, y0) of the drill's motion.
    holding: tuple[float, float, float] | None = None
    #: (capture, stream, pose) of every object keyframe this client sent.
    sent: list[tuple[float, int, tuple[float, ...]]] = field(default_factory=list)
    #: Every capture time of the drill the relay's snapshots brought (the room's times).
    drill_times: set[float] = field(default_factory=set)

    @property
    def user(self) -> int:
        return self.conn.user

    async def receive(self) -> None:
        with contextlib.suppress(ConnectionClosed):
            while True:
                ev = (await self.conn.recv()).event
                if isinstance(ev, Owner):
                    self.owners.append(ev)
                elif isinstance(ev, ObjectInfo):
                    self.infos.append(ev)
                elif isinstance(ev, Snapshot) and self.drill is not None:
                    for i in range(len(ev)):
                        if int(ev.users[i]) == ROOM_USER and int(ev.streams[i]) == self.drill:
                            cap = float(ev.capture_times[i])
                            self.drill_times.add(cap)
                            if self.drill_seen is None or cap > self.drill_seen[0]:
                                self.drill_seen = (cap, tuple(float(x) for x in ev.poses[i]))

    async def publish(self, stop: asyncio.Event) -> None:
        assert self.conn.joined is not None
        head = self.conn.joined.streams["head"]
        seq = 0
        pacer = Pacer(1.0 / RATE)
        while not stop.is_set():
            now = time.monotonic() + self.skew
            ids, poses = [head], [(0.0, 1.6, 0.5 * self.user, 1.0, 0.0, 0.0, 0.0)]
            held = self.drill is not None and self.drill in self.conn.session.held
            if self.holding is not None and self.drill is not None and held:
                t0, x0, y0 = self.holding
                pose = drill_pose(now - t0, x0, y0)
                ids.append(self.drill)
                poses.append(pose)
                self.sent.append((now, self.drill, pose))
            seq += 1
            update = PoseUpdate.from_arrays(seq, ids, [now] * len(ids), np.array(poses))
            with contextlib.suppress(ConnectionClosed):
                await self.conn.send(update)
            await pacer.next()

    def take(self) -> None:
        """Start moving the drill from where this client last saw it."""
        x0, y0 = (0.0, 1.0) if self.drill_seen is None else self.drill_seen[1][:2]
        self.holding = (time.monotonic() + self.skew, x0, max(y0, 0.3))


@dataclass
class Session:
    """The recording and what the clients saw."""

    path: Path
    a: Actor
    b: Actor
    drill: int
    cup: int
    #: Every owner message in the order the relay sent them (as b saw them until it left).
    owners: list[Owner]


#: Poll for a condition; ``limit`` is a hang guard, not a timing check.
_until = partial(poll_until, limit=60.0, every=0.005)


async def _owned(actor: Actor, n: int) -> Owner:
    """Wait for ``actor``'s ``n``-th owner message."""
    await _until(lambda: len(actor.owners) >= n)
    return actor.owners[n - 1]


async def _held(watcher: Actor, keyframes: int) -> None:
    """Wait until ``watcher`` has seen ``keyframes`` more of the drill's keyframes (the
    holder's at 30 Hz, or the relay's while it flies)."""
    start = len(watcher.drill_times)
    await _until(lambda: len(watcher.drill_times) >= start + keyframes)


async def _scene(a: Actor, b: Actor, room: Room) -> tuple[int, int]:
    await a.conn.send(ObjectCreate(name="object:drill", pose=DRILL, steal=True, hold=True))
    await _until(lambda: any(i.name == "object:drill" for i in b.infos))
    drill = next(i.stream for i in a.infos if i.name == "object:drill")
    a.drill = b.drill = drill
    await _owned(a, 1)  # create
    a.take()
    await b.conn.send(ObjectCreate(name="object:cup", pose=CUP, keep=False))
    await _until(lambda: any(i.name == "object:cup" for i in a.infos))
    cup = next(i.stream for i in b.infos if i.name == "object:cup")
    await _held(b, 12)  # about 0.4 s of a's keyframes
    a.holding = None
    await a.conn.send(Release(stream=drill, velocity=(1.0, 2.5, 0.0), angular=(0.0, 3.0, 0.0)))
    await _owned(b, 2)  # throw
    await _held(b, 4)  # a few ticks of flight (it flies about 0.8 s)
    assert room.objects[drill].flight is not None, "landed before the catch"
    await b.conn.send(RequestOwnership(stream=drill))
    await _owned(b, 3)  # catch
    b.take()
    await _held(a, 12)
    b.holding = None
    await b.conn.send(Release(stream=drill))
    await _owned(a, 4)  # release
    await a.conn.send(RequestOwnership(stream=drill))
    await _owned(b, 5)  # request
    a.take()
    await _held(b, 9)  # about 0.3 s
    await b.conn.send(RequestOwnership(stream=drill, steal=True))
    await _owned(a, 6)  # steal
    a.holding = None
    b.take()
    await _held(a, 9)
    b.holding = None
    await b.conn.send(Release(stream=drill, velocity=(0.5, 1.0, 0.0)))
    await _owned(a, 7)  # throw
    await _until(lambda: room.objects[drill].flight is None)  # it lands (0.6 s from 1.2 m)
    await a.conn.send(RequestOwnership(stream=drill, lock=True))
    await _owned(b, 8)  # request (it rests: no catch)
    a.take()
    await _held(b, 9)
    return drill, cup


async def _run(tmp: Path) -> Session:
    # A join waits for the room's recorder (its process starting: seconds on a loaded
    # machine), and the relay's keepalive does not count that wait as an answer.
    # b's skewed captures look 100 ms old to the relay, as a lagging liar's do: the
    # relay's stamp rule (server/stamps.py, tested on its own) would move them, and
    # this session checks that the file keeps what each client sent.
    config = ServerConfig(
        host="127.0.0.1", port=0, record_dir=tmp, ping_timeout=30.0, stamp_lag=0.0
    )
    async with running_server(config) as server:
        url = f"ws://127.0.0.1:{server.port}"
        a = Actor(await ClientConnection.open(url, room=ROOM, streams=("head",), rate=RATE))
        b = Actor(
            await ClientConnection.open(url, room=ROOM, streams=("head",), rate=RATE), skew=SKEW_B
        )
        stop_a, stop_b = asyncio.Event(), asyncio.Event()
        async with asyncio.TaskGroup() as tg:
            for actor, stop in ((a, stop_a), (b, stop_b)):
                tg.create_task(actor.receive())
                tg.create_task(actor.publish(stop))
            try:
                drill, cup = await _scene(a, b, server.rooms[ROOM])
                stop_a.set()
                await a.conn.close()  # leaves holding the drill: owner-left
                await _owned(b, 9)
            finally:
                stop_a.set()
                stop_b.set()
                await a.conn.close()
                await b.conn.close()
    (path,) = server.recordings
    return Session(path, a, b, drill, cup, list(b.owners))


def record_handover_session(tmp: Path) -> Session:
    """Run the scene on a recording relay; the finished recording and what was seen."""
    return asyncio.run(_run(tmp))
