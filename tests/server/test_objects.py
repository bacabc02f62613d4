"""Shared objects (``server/objects.py``): creation, ownership rules, flights, handovers.

The rules on the sans-I/O core with real protocol bytes and fake times; the
loopback test at the end runs them through a real relay with real websocket
clients and a real recording.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from support import poll_until, running_server
from test_core import Client, connect

from posecast.client.connection import ClientConnection
from posecast.protocol import (
    ROOM_USER,
    ErrorMessage,
    Hello,
    Join,
    Joined,
    ObjectCreate,
    ObjectInfo,
    ObjectRemoved,
    Owner,
    PoseUpdate,
    Release,
    RequestOwnership,
    Snapshot,
    encode_message,
)
from posecast.protocol.errors import ErrorCode
from posecast.recorder import SessionReader
from posecast.server.config import ServerConfig
from posecast.server.core import Close, RelayCore
from posecast.server.objects import GRAVITY, Flight

DRILL = (0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0)


def of(client: Client, kind: type) -> list:  # type: ignore[type-arg]
    return [e for e in client.inbox if isinstance(e, kind)]


def errors(client: Client, code: ErrorCode) -> list[ErrorMessage]:
    return [e for e in of(client, ErrorMessage) if e.code == code]


def create(client: Client, now: float, **flags: bool) -> int:
    client.send(ObjectCreate(name="object:drill", pose=DRILL, **flags), now)
    client.read(now)
    return int(of(client, ObjectInfo)[-1].stream)


def hold_update(client: Client, stream: int, capture: float, y: float = 1.2) -> PoseUpdate:
    """An update of the client's head and of object ``stream`` at height ``y``."""
    client.seq += 1
    ids = [client.streams["head"], stream]
    poses = np.array([[0, 1.6, 0, 1, 0, 0, 0], [0.1, y, 0, 1, 0, 0, 0]], dtype=np.float32)
    return PoseUpdate.from_arrays(client.seq, ids, [capture, capture], poses)


def object_entries(core: RelayCore, client: Client, now: float, stream: int) -> list[tuple]:  # type: ignore[type-arg]
    """(user, capture, y) of ``stream`` in the snapshots ``client`` gets at ``now``."""
    core.tick(now)
    out = []
    for snap in [e for e in client.read(now) if isinstance(e, Snapshot)]:
        for i in range(len(snap)):
            if int(snap.streams[i]) == stream:
                out.append(
                    (int(snap.users[i]), float(snap.capture_times[i]), float(snap.poses[i][1]))
                )
    return out


def test_create_tells_everyone_and_a_late_joiner_learns_pose_and_owner() -> None:
    core = RelayCore()
    a, b = connect(core, 1.0), connect(core, 1.1)
    sid = create(a, 1.2, hold=True)
    b.read(1.2)
    for c in (a, b):
        info = of(c, ObjectInfo)[-1]
        assert (info.name, info.stream, info.pose, info.creator) == (
            "object:drill",
            sid,
            DRILL,
            a.user,
        )
        assert of(c, Owner)[-1].owner == a.user and of(c, Owner)[-1].reason == "create"
    assert sid not in a.streams.values() and sid not in b.streams.values()
    # The owner moves it; a late joiner gets it in joined, with its newest pose and owner.
    a.send(hold_update(a, sid, 1.25, y=1.4), 1.26)
    late = connect(core, 1.3)
    joined = of(late, Joined)[-1]
    assert joined.objects == {"object:drill": sid}
    info = of(late, ObjectInfo)[-1]
    assert info.owner == a.user and info.time == 1.25 and abs(info.pose[1] - 1.4) < 1e-6
    assert late.session.objects == {"object:drill": sid}
    # It is in snapshots under the room's user id, whoever publishes it.
    entries = object_entries(core, late, 1.5, sid)
    assert entries and entries[-1][0] == ROOM_USER and abs(entries[-1][2] - 1.4) < 1e-6


def test_ownership_grant_refuse_steal_and_lock() -> None:
    core = RelayCore()
    a, b, c = connect(core, 1.0), connect(core, 1.0), connect(core, 1.0)
    plain = create(a, 1.1)  # nobody holds it; not stealable
    b.send(RequestOwnership(stream=plain), 1.2)
    assert of(b, Owner) == [] and b.read(1.2)
    grant = of(b, Owner)[-1]
    assert (grant.owner, grant.previous, grant.reason) == (b.user, None, "request")
    c.send(RequestOwnership(stream=plain, steal=True), 1.3)
    c.read(1.3)
    refused = errors(c, ErrorCode.OWNERSHIP_REFUSED)
    assert refused and "not stealable" in refused[-1].message and not refused[-1].fatal
    # A stealable object: taken with steal, unless its owner locked it.
    a.send(ObjectCreate(name="object:ball", pose=DRILL, steal=True, hold=True), 1.4)
    ball = next(e.stream for e in a.read(1.4) if isinstance(e, ObjectInfo))
    b.send(RequestOwnership(stream=ball), 1.5)
    b.read(1.5)
    assert "ask with steal" in errors(b, ErrorCode.OWNERSHIP_REFUSED)[-1].message
    b.send(RequestOwnership(stream=ball, steal=True), 1.6)
    c.read(1.6)
    stolen = of(c, Owner)[-1]
    assert (stolen.owner, stolen.previous, stolen.reason) == (b.user, a.user, "steal")
    b.send(RequestOwnership(stream=ball, lock=True), 1.7)
    c.read(1.7)
    assert of(c, Owner)[-1].reason == "lock" and of(c, Owner)[-1].locked
    a.send(RequestOwnership(stream=ball, steal=True), 1.8)
    a.read(1.8)
    assert "locked" in errors(a, ErrorCode.OWNERSHIP_REFUSED)[-1].message
    # Nobody was closed: contention is no misbehaviour.
    assert not [x for x in core._actions() if isinstance(x, Close)]
    assert all(core.peers[x.conn].close_request is None for x in (a, b, c))


def test_release_by_non_owner_refused_and_lost_object_updates_dropped_alone() -> None:
    core = RelayCore()
    a, b = connect(core, 1.0), connect(core, 1.0)
    sid = create(a, 1.1, hold=True, steal=True)
    b.send(Release(stream=sid), 1.2)
    b.read(1.2)
    assert "not held by" in errors(b, ErrorCode.OWNERSHIP_REFUSED)[-1].message
    # b steals it while a's update of it is on its way: the update's object entry is
    # dropped with a non-fatal error, its head pose is taken.
    stale_update = hold_update(a, sid, 1.25)
    b.send(RequestOwnership(stream=sid, steal=True), 1.3)
    core.receive(a.conn, encode_message(stale_update), 1.31)
    a.read(1.31)
    lost = errors(a, ErrorCode.OBJECT_NOT_OWNED)
    assert lost and not lost[-1].fatal and core.peers[a.conn].close_request is None
    head = core.rooms["lobby"].stream_pose(a.streams["head"])
    assert head[0] == 1.25  # the rest of the update went on
    assert core.rooms["lobby"].stream_pose(sid)[0] == 1.1  # the object did not move


def test_updates_of_an_object_never_held_are_still_fatal_for_user_streams() -> None:
    """Naming another user's stream stays the fatal stream-not-owned of before."""
    core = RelayCore()
    a, b = connect(core, 1.0), connect(core, 1.0)
    update = PoseUpdate.from_arrays(1, [b.streams["head"]], [1.1], [DRILL])
    core.receive(a.conn, encode_message(update), 1.1)
    request = core.peers[a.conn].close_request
    assert request is not None and request[0] == 1008


def test_owner_leaving_releases_and_creator_leaving_removes_unkept() -> None:
    core = RelayCore()
    a, b = connect(core, 1.0), connect(core, 1.0)
    kept = create(a, 1.1, hold=True)
    a.send(ObjectCreate(name="object:cup", pose=DRILL, keep=False), 1.2)
    cup = next(e.stream for e in a.read(1.2) if isinstance(e, ObjectInfo))
    core.disconnect(a.conn, 1.3, said_bye=True)
    b.read(1.3)
    left = [e for e in of(b, Owner) if e.reason == "owner-left"]
    assert [(e.stream, e.owner, e.previous) for e in left] == [(kept, None, a.user)]
    assert [(e.stream, e.reason) for e in of(b, ObjectRemoved)] == [(cup, "creator-left")]
    assert set(core.rooms["lobby"].objects) == {kept}
    # The kept one can be taken by anyone now.
    b.send(RequestOwnership(stream=kept), 1.4)
    assert of(b, Owner)[-1].owner != b.user and b.read(1.4) and of(b, Owner)[-1].owner == b.user


def test_parked_owner_keeps_its_object_until_its_window_closes() -> None:
    core = RelayCore(ServerConfig(resume_window=5.0))
    a = Client(core, core.connect(1.0))
    a.send(Hello(agent="t", resumable=True), 1.0)
    a.read(1.0)
    a.send(Join(room="lobby", streams=("head",), rate=10.0), 1.0)
    a.read(1.0)
    b = connect(core, 1.0)
    sid = create(a, 1.1, hold=True)
    core.disconnect(a.conn, 2.0)  # dropped, not a bye: parked
    b.read(2.0)
    assert core.rooms["lobby"].objects[sid].owner == a.user
    b.send(RequestOwnership(stream=sid), 2.5)
    b.read(2.5)
    assert errors(b, ErrorCode.OWNERSHIP_REFUSED)
    core.expire(7.5)
    b.read(7.5)
    assert (
        of(b, Owner)[-1].reason == "owner-left" and core.rooms["lobby"].objects[sid].owner is None
    )


def test_a_thrown_object_flies_and_lands_and_a_catch_ends_the_flight() -> None:
    core = RelayCore()
    a, b = connect(core, 1.0, rate=20.0), connect(core, 1.0, rate=20.0)
    sid = create(a, 1.0, hold=True)
    a.send(hold_update(a, sid, 1.05, y=1.0), 1.06)
    a.send(Release(stream=sid, velocity=(1.0, 2.0, 0.0), angular=(0.0, 3.0, 0.0)), 1.07)
    throw = [e for e in b.read(1.07) if isinstance(e, Owner)][-1]
    assert throw.reason == "throw" and throw.owner is None and throw.velocity == (1.0, 2.0, 0.0)
    heights = []
    for k in range(1, 20):
        heights += [(t, y) for _, t, y in object_entries(core, b, 1.05 + 0.05 * k, sid)]
    flight = Flight(1.05, (0.1, 1.0, 0, 1, 0, 0, 0), (1.0, 2.0, 0.0), (0.0, 3.0, 0.0), 0.0)
    for t, y in heights:
        dt = min(t - 1.05, flight.landing())
        assert abs(y - (1.0 + 2.0 * dt - 0.5 * GRAVITY * dt * dt)) < 1e-4
    assert max(y for _, y in heights) > 1.15 and heights[-1][1] == 0.0  # up, then on the floor
    assert core.rooms["lobby"].objects[sid].flight is None
    # Throw again and catch it mid-air: the catcher owns it, the flight ends.
    a.send(RequestOwnership(stream=sid), 2.3)
    a.send(Release(stream=sid, velocity=(0.0, 4.0, 0.0)), 2.31)
    object_entries(core, b, 2.4, sid)
    b.send(RequestOwnership(stream=sid), 2.42)
    catch = [e for e in b.read(2.42) if isinstance(e, Owner)][-1]
    assert (catch.reason, catch.owner) == ("catch", b.user)
    assert core.rooms["lobby"].objects[sid].flight is None


def test_a_new_owner_behind_in_time_is_shifted_after_the_last_keyframe() -> None:
    core = RelayCore()
    a, b = connect(core, 1.0), connect(core, 1.0)
    sid = create(a, 1.0, hold=True)
    a.send(hold_update(a, sid, 2.00), 2.01)
    a.send(Release(stream=sid), 2.02)
    b.send(RequestOwnership(stream=sid), 2.03)
    b.read(2.03)
    # b's clock estimate runs 30 ms behind a's: its first keyframe is stamped 1.98.
    b.send(hold_update(b, sid, 1.98), 2.04)
    b.send(hold_update(b, sid, 2.03), 2.09)
    room = core.rooms["lobby"]
    assert abs(room.stream_pose(sid)[0] - (2.03 + 0.021)) < 1e-9  # 1.98 -> 2.001
    # The intervals between its keyframes are its own.
    assert room.objects[sid].offset > 0.0


def test_spectators_create_nothing_and_limits_hold() -> None:
    core = RelayCore(ServerConfig(max_objects=1))
    a = connect(core, 1.0)
    s = Client(core, core.connect(1.0))
    s.send(Hello(agent="v"), 1.0)
    s.read(1.0)
    s.send(Join(room="lobby", streams=("head",), rate=10.0, spectator=True), 1.0)
    s.read(1.0)
    s.send(ObjectCreate(name="object:x", pose=DRILL), 1.1)
    s.read(1.1)
    assert errors(s, ErrorCode.OWNERSHIP_REFUSED)
    a.send(ObjectCreate(name="object:far", pose=(0.0, 50.0, 0.0, 1.0, 0.0, 0.0, 0.0)), 1.15)
    a.read(1.15)
    assert "outside the room volume" in errors(a, ErrorCode.BAD_POSE)[-1].message
    create(a, 1.2)
    a.send(ObjectCreate(name="object:drill", pose=DRILL), 1.3)
    a.send(ObjectCreate(name="object:two", pose=DRILL), 1.3)
    a.read(1.3)
    messages = [e.message for e in errors(a, ErrorCode.OWNERSHIP_REFUSED)]
    assert any("exists" in m for m in messages) and any("1 objects" in m for m in messages)
    a.send(RequestOwnership(stream=999), 1.4)
    a.read(1.4)
    assert "no object" in errors(a, ErrorCode.OWNERSHIP_REFUSED)[-1].message


async def test_throw_and_catch_over_a_real_relay_is_seen_and_recorded(tmp_path: Path) -> None:
    """Real relay, real websocket clients, a real recording: a creates and holds the
    drill, moves it, throws it; b sees it fly under ROOM_USER and catches it; the
    file holds the object's life, the ownership changes and the flight."""
    config = ServerConfig(host="127.0.0.1", port=0, record_dir=tmp_path)
    async with running_server(config) as srv:
        url = f"ws://127.0.0.1:{srv.port}"
        a = await ClientConnection.open(url, room="r", streams=("head",), rate=20.0)
        await a.send(ObjectCreate(name="object:drill", pose=DRILL, hold=True))
        sid = await _until(a, lambda e: isinstance(e, Owner) and e.owner == a.user)
        b = await ClientConnection.open(url, room="r", streams=("head",), rate=20.0)
        assert b.joined is not None and b.joined.objects == {"object:drill": sid.stream}
        assert b.session.objects == {"object:drill": sid.stream}
        head = b.joined.streams["head"]
        for k in range(5):  # a carries it up to 1.2 m
            now = time.monotonic()
            poses = np.array([[0, 1.6, 0, 1, 0, 0, 0], [0, 1.0 + 0.05 * k, 0, 1, 0, 0, 0]])
            ids = [a.joined.streams["head"], sid.stream]  # type: ignore[union-attr]
            await a.send(PoseUpdate.from_arrays(k + 1, ids, [now, now], poses))
            handled = partial(lambda n: srv.rooms["r"].statistics().updates_in >= n, k + 1)
            await poll_until(handled, every=0.005)  # taken in before the next
        await a.send(Release(stream=sid.stream, velocity=(0.5, 3.0, 0.0)))
        heights: list[tuple[float, float]] = []

        def flying(event: object) -> bool:
            if isinstance(event, Snapshot):
                for i in range(len(event)):
                    if int(event.streams[i]) == sid.stream and int(event.users[i]) == ROOM_USER:
                        heights.append((float(event.capture_times[i]), float(event.poses[i][1])))
            return len(heights) >= 8 and heights[-1][1] > heights[-2][1] - 1.0

        await _until(b, flying)
        ys = [y for _, y in heights]
        assert max(ys) > 1.25 and len(set(ys)) > 3  # it rose above the release height
        await b.send(RequestOwnership(stream=sid.stream))
        catch = await _until(b, lambda e: isinstance(e, Owner) and e.owner == b.user)
        assert catch.reason in ("catch", "request") and catch.previous is None
        assert sid.stream in b.session.held
        now = time.monotonic()
        await b.send(PoseUpdate.from_arrays(1, [head, sid.stream], [now, now], [DRILL, DRILL]))
        await a.close()
        await b.close()
    (path,) = srv.recordings
    with SessionReader(path) as reader:
        kinds = [
            (e.kind, e.data.get("user"), e.data["payload"].get("reason"))
            for e in reader.events()
            if e.kind in ("object_create", "owner", "object_remove")
        ]
        flight = [p for p in reader.poses() if p.user == ROOM_USER]
    # Created, held by a, thrown, caught by b, released when b left.
    assert kinds == [
        ("object_create", 0, None),
        ("owner", 0, "create"),
        ("owner", None, "throw"),
        ("owner", 1, catch.reason),
        ("owner", None, "owner-left"),
    ]
    assert flight and all(p.velocities is not None for p in flight)
    assert {int(s) for p in flight for s in p.streams} == {sid.stream}


async def _until(conn: ClientConnection, check: Callable[[object], bool]) -> Any:
    """The first event of ``conn`` that passes ``check`` (within 10 s)."""
    async with asyncio.timeout(10):
        while True:
            event = (await conn.recv()).event
            if check(event):
                return event


def test_a_creation_time_keeps_the_creators_next_keyframes_unshifted() -> None:
    """object_create.time: the creator's keyframes captured after it go in as they are;
    a time outside the capture limits is refused."""
    core = RelayCore()
    a = connect(core, 1.0)
    a.send(ObjectCreate(name="object:drill", pose=DRILL, hold=True, time=1.95), 2.0)
    sid = next(e.stream for e in a.read(2.0) if isinstance(e, ObjectInfo))
    assert core.rooms["lobby"].stream_pose(sid)[0] == 1.95
    a.send(hold_update(a, sid, 1.97), 2.01)  # captured before the create arrived
    assert core.rooms["lobby"].stream_pose(sid)[0] == 1.97
    assert core.rooms["lobby"].objects[sid].offset == 0.0
    a.send(ObjectCreate(name="object:late", pose=DRILL, time=0.5), 2.1)
    a.read(2.1)
    assert "object_create.time" in errors(a, ErrorCode.BAD_POSE)[-1].message
