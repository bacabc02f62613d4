"""Forwarding between cluster nodes (``server/forward.py``) over a real nats-server.

An owner node's relay core hosts a room with one local member and one member
whose socket is on another node (the edge): the edge welcomed it with an id of
its own block, forwards its frames over NATS, and delivers what the owner
sends back. Both members see each other as on one server: peer notices, each
other's poses in snapshots, events in order, clock sync against the owner,
and errors and closes from the owner's rules.
"""

from __future__ import annotations

import asyncio
from functools import partial

import msgpack
import nats
import numpy as np
from conftest import needs_nats
from nats.aio.msg import Msg
from support import poll_until
from test_core import connect

from posecast.protocol import (
    ClientSession,
    ErrorMessage,
    Hello,
    Join,
    Joined,
    PeerJoined,
    Ping,
    Pong,
    PoseUpdate,
    ProtocolError,
    Snapshot,
    UserEvent,
    Welcome,
)
from posecast.server.core import RelayCore
from posecast.server.forward import Edge, Members, _batch_items
from posecast.server.room import IdAllocator

pytestmark = needs_nats

POSE = np.array([[0.0, 1.6, 0.0, 1.0, 0.0, 0.0, 0.0]])


class Remote:
    """A client whose socket is on the edge node: its session, what it got, its close."""

    def __init__(self) -> None:
        self.session = ClientSession()
        self.inbox: list[object] = []
        self.closed: tuple[int, str] | None = None

    def got(self, kind: type) -> list:  # type: ignore[type-arg]
        return [e for e in self.inbox if isinstance(e, kind)]


_until = partial(poll_until, limit=10.0, every=0.01)


async def test_a_member_through_another_node_is_one_of_the_room(nats_url: str) -> None:
    now = 100.0
    owner = RelayCore()
    owner.users = IdAllocator(1024, start=0)  # node index 0's block
    edge_core = RelayCore()
    edge_core.users = IdAllocator(2048, start=1024)  # node index 1's block
    nc_owner, nc_edge = await nats.connect(nats_url), await nats.connect(nats_url)
    applied: list[object] = []
    members = Members(owner, nc_owner, "o", applied.extend, clock=lambda: now)
    remote = Remote()

    def deliver(econn: int, data: bytes) -> None:
        remote.inbox.extend(remote.session.receive_data(data))

    def close(econn: int, code: int, reason: str) -> None:
        remote.closed = (code, reason)

    edge = Edge(nc_edge, "e", deliver, close)
    await members.start()
    await edge.start()
    try:
        async with asyncio.TaskGroup() as tg:
            writer = tg.create_task(members.run())
            sender = tg.create_task(edge.run())
            local = connect(owner, now, room="lab", rate=20.0)
            # The edge welcomes its client (an id of its block), then the join goes on.
            econn = edge_core.connect(now)
            for frame in edge_core.take(econn, now)[0]:
                deliver(econn, frame)
            edge_core.receive(econn, remote.session.send(Hello(agent="far")), now)
            for frame in edge_core.take(econn, now)[0]:
                deliver(econn, frame)
            user = remote.got(Welcome)[0].user
            assert 1024 <= user < 2048
            edge.open(econn, "o", user, "far", False, "10.0.0.9")
            join = remote.session.send(Join(room="lab", streams=("head", "left"), rate=20.0))
            edge.forward(econn, [join])
            await _until(lambda: bool(remote.got(Joined)))
            joined = remote.got(Joined)[0]
            await _until(lambda: bool(remote.got(PeerJoined)))
            assert [p.user for p in remote.got(PeerJoined)] == [local.user]
            # The remote member publishes; the local one gets its poses, and back.
            ids = [joined.streams["head"], joined.streams["left"]]
            update = PoseUpdate.from_arrays(1, ids, [now, now], np.repeat(POSE, 2, axis=0))
            edge.forward(econn, [remote.session.send(update)])
            await _until(lambda: members.frames_in >= 2)
            local.publish(now)
            now += 0.05
            members.route(owner.tick(now))
            snaps = [e for e in local.read(now) if isinstance(e, Snapshot)]
            assert snaps and user in set(snaps[-1].users.tolist())
            # Presence goes out at the room's tick (``server.presence``).
            assert [e.user for e in local.inbox if isinstance(e, PeerJoined)] == [user]
            await _until(lambda: bool(remote.got(Snapshot)))
            assert local.user in set(remote.got(Snapshot)[-1].users.tolist())
            # Events in order, and pings answered on the owner's clock.
            for k in range(5):
                local.send(UserEvent(kind="button", payload={"k": k}), now)
            edge.forward(econn, [remote.session.send(Ping(seq=1, time=7.0))])
            await _until(lambda: len(remote.got(UserEvent)) == 5 and bool(remote.got(Pong)))
            assert [e.payload["k"] for e in remote.got(UserEvent)] == [0, 1, 2, 3, 4]
            assert remote.got(Pong)[0].recv_time == now
            # A frame the owner's rules refuse: its error, then the close, reach the edge.
            edge.forward(econn, [b"\x00not msgpack"])
            await _until(lambda: remote.closed is not None)
            assert remote.closed is not None and remote.closed[0] == 1002
            assert remote.got(ErrorMessage)[-1].code == "bad-frame"
            edge.gone(econn, said_bye=False)
            await _until(lambda: not members.conns)
            local.read(now)
            writer.cancel()
            sender.cancel()
    finally:
        await nc_owner.close()
        await nc_edge.close()


async def test_one_message_per_edge_carries_a_shared_snapshot_once(nats_url: str) -> None:
    """Three members on one edge: a tick's shared snapshot crosses NATS once, with
    the three of them as its targets."""
    now = 50.0
    owner = RelayCore()
    nc_owner, nc_edge = await nats.connect(nats_url), await nats.connect(nats_url)
    members = Members(owner, nc_owner, "o", lambda actions: None, clock=lambda: now)
    sessions = {e: ClientSession() for e in (1, 2, 3)}
    got: dict[int, list[object]] = {e: [] for e in sessions}
    messages: list[list[object]] = []

    def deliver(econn: int, data: bytes) -> None:
        got[econn].extend(sessions[econn].receive_data(data))

    edge = Edge(nc_edge, "e", deliver, lambda econn, code, reason: None)
    await members.start()
    await edge.start()

    async def tap(msg: Msg) -> None:
        messages.append(msgpack.unpackb(msg.data))

    await nc_edge.subscribe("posecast.node.e.out", cb=tap)
    try:
        async with asyncio.TaskGroup() as tg:
            writer = tg.create_task(members.run())
            sender = tg.create_task(edge.run())
            pub = connect(owner, now, room="lab", rate=20.0)
            for econn, session in sessions.items():
                await _open_remote(edge, members, session, got[econn], econn, now)
            pub.publish(now)
            messages.clear()
            now += 0.05
            members.route(owner.tick(now))
            await _until(lambda: all(any(isinstance(x, Snapshot) for x in got[e]) for e in got))
            frames = [item for m in messages if m[0] == "frames" for item in m[1:]]
            snapshots = [t for t, data in frames if msgpack.unpackb(data)["type"] == "snapshot"]
            assert [sorted(targets) for targets in snapshots] == [[1, 2, 3]]
            writer.cancel()
            sender.cancel()
    finally:
        await nc_owner.close()
        await nc_edge.close()


async def _open_remote(
    edge: Edge,
    members: Members,
    session: ClientSession,
    inbox: list[object],
    econn: int,
    now: float,
) -> None:
    """Welcome ``session`` on the edge (:func:`_welcome_on_edge`), then join room
    "lab" on the owner."""
    _welcome_on_edge(edge, session, inbox, econn, now)
    edge.forward(econn, [session.send(Join(room="lab", streams=("head",), rate=20.0))])
    await _until(lambda: any(isinstance(e, Joined) for e in inbox))


def _welcome_on_edge(
    edge: Edge, session: ClientSession, inbox: list[object], econn: int, now: float
) -> None:
    """Welcome ``session`` as the edge's core would (an id of the edge's block), then
    open it on the owner."""
    edge_core = RelayCore()
    edge_core.users = IdAllocator(1024 + econn + 1, start=1024 + econn)
    conn = edge_core.connect(now)
    edge_core.receive(conn, session.send(Hello(agent="far")), now)
    for frame in edge_core.take(conn, now)[0]:
        inbox.extend(session.receive_data(frame))
    user = next(e.user for e in inbox if isinstance(e, Welcome))
    edge.open(econn, "o", user, "far", False, "x")


async def test_a_new_member_gets_joined_before_a_shared_snapshot(nats_url: str) -> None:
    """A remote member joins and the room ticks before the owner writes to its edge:
    the tick's snapshot is shared with a member already there, and each client still
    gets its frames in order (``joined`` first: a snapshot before it is a protocol
    error that ends the client's join)."""
    now = 50.0
    owner = RelayCore()
    nc_owner, nc_edge = await nats.connect(nats_url), await nats.connect(nats_url)
    members = Members(owner, nc_owner, "o", lambda actions: None, clock=lambda: now)
    sessions = {e: ClientSession() for e in (1, 2)}
    got: dict[int, list[object]] = {e: [] for e in sessions}

    def deliver(econn: int, data: bytes) -> None:
        got[econn].extend(sessions[econn].receive_data(data))

    edge = Edge(nc_edge, "e", deliver, lambda econn, code, reason: None)
    await members.start()
    await edge.start()
    try:
        async with asyncio.TaskGroup() as tg:
            sender = tg.create_task(edge.run())
            writer = tg.create_task(members.run())
            pub = connect(owner, now, room="lab", rate=20.0)
            await _open_remote(edge, members, sessions[1], got[1], 1, now)
            writer.cancel()  # from here on the owner writes only when told to
            _welcome_on_edge(edge, sessions[2], got[2], 2, now)
            seen = members.frames_in
            edge.forward(2, [sessions[2].send(Join(room="lab", streams=("head",), rate=20.0))])
            await _until(lambda: members.frames_in > seen)
            pub.publish(now)
            now += 0.05
            members.route(owner.tick(now))  # the tick comes before the owner's write
            await members.flush()
            await _until(lambda: any(isinstance(e, Snapshot | ProtocolError) for e in got[2]))
            kinds = [type(e).__name__ for e in got[2]]
            assert not [e for e in got[2] if isinstance(e, ProtocolError)], kinds
            assert kinds.index("Joined") < kinds.index("Snapshot"), kinds
            assert any(isinstance(e, Snapshot) for e in got[1])
            sender.cancel()
    finally:
        await nc_owner.close()
        await nc_edge.close()


def test_frames_shared_in_opposite_orders_are_not_shared() -> None:
    """Each edge connection gets its frames in its own order, whatever is shared."""
    a, b, own = b"tick-1", b"tick-2", b"joined"
    assert _batch_items([(1, [a, b]), (2, [own, a, b])]) == [[[2], own], [[1, 2], a], [[1, 2], b]]
    # Opposite orders cannot be one sequence: nothing is shared then.
    assert _batch_items([(1, [a, b]), (2, [b, a])]) == [[[1], a], [[1], b], [[2], b], [[2], a]]
