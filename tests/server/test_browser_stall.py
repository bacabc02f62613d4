"""A publisher whose socket stays up but whose updates stop (a frozen browser tab) is
announced ``peer_stalled`` after ``stall_after``, and ``peer_resumed`` when they come back.

Sans-I/O on the core with the time as an argument (``test_core.py``'s clients), then
once over real sockets on a real relay.
"""

from __future__ import annotations

import asyncio

import numpy as np
from support import running_server
from test_core import POSE, connect
from test_resume import hello, join, kinds

from posecast.client.connection import ClientConnection
from posecast.protocol import PeerLeft, PeerResumed, PeerStalled, PoseUpdate
from posecast.server.core import RelayCore, ServerConfig

STREAMS = ("head", "left", "right")


def _expire_at(core: RelayCore, now: float) -> None:
    """What the adapter's expiry loop does when ``next_expiry`` is due."""
    core.expire(now)


def test_silence_is_announced_after_the_bound_and_resume_at_the_next_update() -> None:
    """Updates stop at 1.5: peers hear peer_stalled at 2.5 (not before), peer_resumed at
    the next update; a member that never published is never announced."""
    core = RelayCore(ServerConfig(stall_after=1.0))
    a, b = connect(core, 1.0), connect(core, 1.0)
    a.read(1.0), b.read(1.0)
    for k in range(6):
        a.publish(1.0 + 0.1 * k)
    assert core.next_expiry() is not None
    _expire_at(core, 2.49)
    assert kinds(b.read(2.49)) == []
    due = core.next_expiry()
    assert due is not None and abs(due - 2.5) < 1e-9
    _expire_at(core, due)
    stalled = [e for e in b.read(due) if isinstance(e, PeerStalled)]
    assert [e.user for e in stalled] == [a.user]
    assert not [e for e in a.read(due) if isinstance(e, PeerStalled)]  # b never published
    assert core.silence.stalls == 1
    _expire_at(core, 5.0)  # announced once, not again while it stays silent
    assert kinds(b.read(5.0)) == []
    a.publish(5.1)
    assert [e.user for e in b.read(5.1) if isinstance(e, PeerResumed)] == [a.user]
    assert core.silence.resumes == 1
    # Watched again: silence after the resume is announced anew.
    due = core.next_expiry()
    assert due is not None and abs(due - 6.1) < 1e-9
    _expire_at(core, due)
    assert kinds(b.read(due)) == [PeerStalled]


def test_a_steady_publisher_is_never_announced() -> None:
    """Updates every 0.2 s against a 1 s bound: every deadline met moves on, no notice."""
    core = RelayCore(ServerConfig(stall_after=1.0))
    a, b = connect(core, 1.0), connect(core, 1.0)
    a.read(1.0), b.read(1.0)
    now = 1.0
    while now < 10.0:
        a.publish(now)
        due = core.next_expiry()
        assert due is not None and due > now
        if due <= now + 0.2:
            _expire_at(core, due)
        now += 0.2
    assert kinds(b.read(now)) == [] and core.silence.stalls == 0


def test_stall_after_zero_turns_it_off() -> None:
    """stall_after=0: no deadline is ever set, no notice."""
    core = RelayCore(ServerConfig(stall_after=0.0))
    a, b = connect(core, 1.0), connect(core, 1.0)
    a.read(1.0), b.read(1.0)
    a.publish(1.0)
    assert core.next_expiry() is None  # (both joined: no join deadline either)
    _expire_at(core, 30.0)
    assert not [e for e in b.read(30.0) if isinstance(e, PeerStalled)]


def test_a_silent_member_that_drops_is_not_announced_twice() -> None:
    """Silent, then its socket drops (parked): one peer_stalled in all; its resume brings
    one peer_resumed; the window closing after a drop still says peer_left."""
    core = RelayCore(ServerConfig(stall_after=1.0, resume_window=10.0))
    a, wa = hello(core, 1.0)
    join(a, 1.0)
    b, _ = hello(core, 1.0)
    join(b, 1.0)
    b.read(1.0)
    a.publish(1.1)
    _expire_at(core, 2.1)
    core.disconnect(a.conn, 2.5)
    assert kinds(b.read(2.5)) == [PeerStalled]
    back, _ = hello(core, 3.0, resume=wa.resume)
    back.streams = join(back, 3.0).streams
    assert kinds(b.read(3.0)) == [PeerResumed]
    # Resumed, and watched from its resume: silence is announced again.
    _expire_at(core, 3.99)
    assert kinds(b.read(3.99)) == []
    _expire_at(core, 4.0)
    assert kinds(b.read(4.0)) == [PeerStalled]
    back.publish(4.2)
    assert kinds(b.read(4.2)) == [PeerResumed]
    core.disconnect(back.conn, 4.5)
    _expire_at(core, 20.0)
    core.tick(20.0)  # presence notices go out at the room's tick
    assert kinds(b.read(20.0)) == [PeerStalled, PeerLeft]


async def test_a_socket_that_stops_publishing_is_announced_over_real_sockets() -> None:
    """Over a real relay: a client that stops publishing but keeps its socket (and
    answers pings) is announced stalled to its peer, and resumed when it publishes."""
    cfg = ServerConfig(host="127.0.0.1", port=0, stall_after=0.3, ping_interval=0.1)
    async with running_server(cfg) as srv:
        url = f"ws://127.0.0.1:{srv.port}"
        watcher = await ClientConnection.open(url, room="r", streams=STREAMS, rate=20)
        quiet = await ClientConnection.open(url, room="r", streams=STREAMS, rate=20)
        assert quiet.welcome is not None and quiet.joined is not None
        ids = list(quiet.joined.streams.values())

        async def publish(seq: int) -> None:
            await quiet.send(PoseUpdate.from_arrays(seq, ids, np.full(3, quiet.clock()), POSE))

        async def notices(want: int) -> list[object]:
            got: list[object] = []
            async with asyncio.timeout(10):
                while len(got) < want:
                    event = (await watcher.recv()).event
                    if isinstance(event, PeerStalled | PeerResumed | PeerLeft):
                        got.append(event)
            return got

        await publish(1)
        (stalled,) = await notices(1)  # nothing more is sent: silent after 0.3 s
        assert isinstance(stalled, PeerStalled) and stalled.user == quiet.welcome.user
        await publish(2)
        (resumed,) = await notices(1)
        assert isinstance(resumed, PeerResumed) and resumed.user == quiet.welcome.user
        assert srv.core.silence.stalls == srv.core.silence.resumes == 1
        await watcher.close()
        await quiet.close()
