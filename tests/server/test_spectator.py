"""Spectators (``Join.spectator``): they watch, publish nothing, and nobody hears of them.

The rules on the sans-I/O core with real protocol bytes and fake times, then
once over a real relay on loopback with real websocket clients.
"""

from __future__ import annotations

import asyncio
import contextlib
import time

import numpy as np
from support import Pacer, poll_until, running_server
from test_core import Client, connect
from websockets.exceptions import ConnectionClosed

from posecast.client.connection import ClientConnection
from posecast.protocol import (
    ErrorMessage,
    Hello,
    Join,
    PeerJoined,
    PeerLeft,
    Ping,
    Pong,
    PoseUpdate,
    Snapshot,
    UserEvent,
)
from posecast.server.core import Close, RelayCore

POSE = np.array([[0.0, 1.6, 0.0, 1.0, 0.0, 0.0, 0.0]], dtype=np.float32)


def spectate(core: RelayCore, now: float, room: str = "lobby") -> Client:
    """A client joined to ``room`` as a spectator (one nominal stream)."""
    c = Client(core, core.connect(now))
    c.send(Hello(agent="viewer"), now)
    c.read(now)
    c.send(Join(room=room, streams=("head",), rate=10.0, spectator=True), now)
    c.read(now)
    return c


def test_spectator_is_announced_to_nobody() -> None:
    """Members never get peer_joined/peer_left for a spectator; it gets theirs."""
    core = RelayCore()
    a = connect(core, 1.0)
    s = spectate(core, 1.1)
    b = connect(core, 1.2)
    assert [e.user for e in s.inbox if isinstance(e, PeerJoined)] == [a.user]
    core.tick(1.2)  # presence notices go out at the room's tick
    s.read(1.2)
    assert sorted(e.user for e in s.inbox if isinstance(e, PeerJoined)) == [a.user, b.user]
    a.read(1.2)
    assert [e.user for e in a.inbox if isinstance(e, PeerJoined)] == [b.user]
    assert [e.user for e in b.inbox if isinstance(e, PeerJoined)] == [a.user]
    # The spectator leaves: nobody hears of it; a member leaves: the spectator hears.
    core.disconnect(s.conn, 1.4)
    core.tick(1.4)
    a.read(1.4)
    assert not [e for e in a.inbox if isinstance(e, PeerLeft)]
    s2 = spectate(core, 1.5)
    core.disconnect(b.conn, 1.6)
    core.tick(1.6)
    assert [e.user for e in s2.read(1.6) if isinstance(e, PeerLeft)] == [b.user]


def test_two_spectators_do_not_see_each_other() -> None:
    """A spectator is not announced to another spectator either."""
    core = RelayCore()
    s1 = spectate(core, 1.0)
    s2 = spectate(core, 1.1)
    assert not [e for e in s1.read(1.1) + s2.inbox if isinstance(e, PeerJoined)]


def test_spectator_receives_snapshots() -> None:
    """A spectator is ticked like any member and gets the room's poses."""
    core = RelayCore()
    a = connect(core, 1.0)
    s = spectate(core, 1.0)
    a.publish(1.01)
    due = core.next_deadline()
    assert due is not None
    core.tick(due)
    snaps = [e for e in s.read(due) if isinstance(e, Snapshot)]
    assert len(snaps) == 1
    assert sorted(snaps[0].entries["stream"].tolist()) == sorted(a.streams.values())


def test_spectator_update_is_refused_not_owned() -> None:
    """An update from a spectator is stream-not-owned (fatal, 1008) and reaches nobody."""
    core = RelayCore()
    a = connect(core, 1.0)
    s = spectate(core, 1.0)
    a.read(1.0)
    sid = s.streams["head"]
    update = PoseUpdate.from_arrays(1, [sid], np.array([1.05]), POSE)
    actions = s.send(update, 1.05)
    assert [(x.code, x.reason) for x in actions if isinstance(x, Close)] == [
        (1008, "spectators publish nothing")
    ]
    errors = [e for e in s.read(1.05) if isinstance(e, ErrorMessage)]
    assert [(e.code, e.fatal, e.in_reply_to) for e in errors] == [
        ("stream-not-owned", True, "update")
    ]
    due = core.next_deadline()
    assert due is not None
    core.tick(due)
    assert not [e for e in a.read(due) if isinstance(e, Snapshot)]


def test_spectator_event_is_refused() -> None:
    """An event from a spectator is refused the same way and is not relayed."""
    core = RelayCore()
    a = connect(core, 1.0)
    s = spectate(core, 1.0)
    a.read(1.0)
    actions = s.send(UserEvent(kind="button"), 1.1)
    assert [x.code for x in actions if isinstance(x, Close)] == [1008]
    assert not [e for e in a.read(1.1) if isinstance(e, UserEvent)]


async def test_spectator_over_a_real_relay() -> None:
    """Over websockets: the spectator gets the poses; the publisher never hears of it."""
    async with running_server() as srv:
        url = f"ws://127.0.0.1:{srv.port}"
        pub = await ClientConnection.open(url, room="r", streams=("head",), rate=20.0)
        spec = await ClientConnection.connect(url, agent="viewer")
        await spec.send(Join(room="r", streams=("head",), rate=20.0, spectator=True))
        assert pub.joined is not None
        sid = pub.joined.streams["head"]
        peers: list[int] = []
        xs: list[float] = []
        heard: list[object] = []

        async def watch() -> None:
            while len(xs) < 3:
                ev = (await spec.recv()).event
                if isinstance(ev, PeerJoined):
                    peers.append(ev.user)
                elif isinstance(ev, Snapshot):
                    xs.extend(float(ev.poses[i][0]) for i in range(len(ev)))

        async def publish() -> None:
            # The relay runs on this process's monotonic clock: capture times are "now".
            pacer = Pacer(0.02)
            for seq in range(1, 10_000):
                pose = POSE.copy()
                pose[0, 0] = seq / 1000
                now = time.monotonic()
                await pub.send(PoseUpdate.from_arrays(seq, [sid], [now], pose, base_time=now))
                await pacer.next()

        async def listen() -> None:
            with contextlib.suppress(ConnectionClosed):
                while True:
                    heard.append((await pub.recv()).event)

        async with asyncio.TaskGroup() as tg:
            tasks = [tg.create_task(publish()), tg.create_task(listen())]
            await asyncio.wait_for(watch(), 20)
            await spec.close()
            await poll_until(lambda: srv.closed_connections == 1)  # the relay saw it go
            # A ping round trip: a peer_left queued for pub at the close is in by now.
            await pub.send(Ping(seq=1, time=time.monotonic()))
            await poll_until(lambda: any(isinstance(e, Pong) for e in heard))
            for t in tasks:
                t.cancel()
        await pub.close()
    assert peers == [pub.user]
    # Every pose the spectator got is one the publisher sent (x = seq / 1000).
    assert xs and all(0 < x < 10 and abs(x * 1000 - round(x * 1000)) < 1e-3 for x in xs)
    assert not [e for e in heard if isinstance(e, PeerJoined | PeerLeft)]
