"""Resume after a dropped connection: same user and stream ids, no leave/join for peers.

Sans-I/O like ``test_core.py`` (time is an argument), then once over real
sockets: a client whose TCP connection is cut reconnects with its token.
"""

from __future__ import annotations

import asyncio

import numpy as np
from support import running_server
from test_core import POSE, Client

from posecast.client.connection import ClientConnection
from posecast.protocol import (
    Bye,
    Hello,
    Join,
    Joined,
    PeerJoined,
    PeerLeft,
    PeerResumed,
    PeerStalled,
    PoseUpdate,
    Snapshot,
    UserEvent,
    Welcome,
)
from posecast.server.core import RelayCore, ServerConfig

STREAMS = ("head", "left", "right")


def hello(core: RelayCore, now: float, resume: str | None = None) -> tuple[Client, Welcome]:
    c = Client(core, core.connect(now))
    c.send(Hello(agent="r", resumable=True, resume=resume), now)
    (welcome,) = [e for e in c.read(now) if isinstance(e, Welcome)]
    return c, welcome


def join(c: Client, now: float, streams: tuple[str, ...] = STREAMS) -> Joined:
    c.send(Join(room="lobby", streams=streams, rate=10.0), now)
    (joined,) = [e for e in c.read(now) if isinstance(e, Joined)]
    return joined


def pair(core: RelayCore) -> tuple[Client, Welcome, Client]:
    """A resumable member a and a member b in one room; b has read everything."""
    a, wa = hello(core, 1.0)
    join(a, 1.0)
    b, _ = hello(core, 1.0)
    join(b, 1.0)
    b.read(1.0)
    return a, wa, b


def kinds(events: list[object]) -> list[type]:
    return [type(e) for e in events if not isinstance(e, Snapshot)]


def test_a_dropped_member_resumes_with_the_same_ids_and_no_leave() -> None:
    core = RelayCore()
    a, wa = hello(core, 1.0)
    assert wa.resume and not wa.resumed
    ja = join(a, 1.0)
    b, _ = hello(core, 1.0)
    join(b, 1.0)
    b.read(1.0)
    a.publish(1.1)
    core.disconnect(a.conn, 2.0)  # the socket dropped: no bye
    since = len(b.inbox)
    assert kinds(b.read(2.0)) == [PeerStalled]
    # An event for the stalled member waits in its queue.
    b.send(UserEvent(kind="grab", stream=b.streams["head"], time=2.1), 2.1)
    back, wb = hello(core, 3.0, resume=wa.resume)
    assert wb.resumed and wb.user == wa.user and wb.resume != wa.resume
    jb = join(back, 3.0)
    assert jb.streams == ja.streams
    got = back.inbox
    # The room anew (its peer), then the event it missed while stalled.
    assert [type(e) for e in got if isinstance(e, UserEvent | PeerJoined)] == [
        PeerJoined,
        UserEvent,
    ]
    assert kinds(b.read(3.0)) == [PeerResumed]
    # It publishes on, under the same stream ids, and b never saw it leave.
    back.streams = jb.streams
    back.publish(3.2)
    later = b.inbox[since:] + b.read(3.3)
    assert not [e for e in later if isinstance(e, PeerLeft | PeerJoined)]
    core.tick(core.next_deadline() or 4.0)
    snaps = [e for e in b.read(4.0) if isinstance(e, Snapshot)]
    assert any(wa.user in s.entries["user"] for s in snaps)
    assert core.parking.resumes == 1


def test_the_window_closes_and_the_member_leaves_as_gone() -> None:
    core = RelayCore(ServerConfig(resume_window=10.0))
    a, wa, b = pair(core)
    core.disconnect(a.conn, 2.0)
    assert core.next_expiry() == 12.0
    core.expire(11.9)
    assert kinds(b.read(11.9)) == [PeerStalled]
    core.expire(12.0)
    core.tick(12.0)  # presence notices go out at the room's tick
    (left,) = [e for e in b.read(12.0) if isinstance(e, PeerLeft)]
    assert (left.user, left.reason) == (wa.user, "gone")
    assert wa.user not in core.rooms["lobby"].members
    # The token is spent with the window: a late resume is a new user.
    _, late = hello(core, 13.0, resume=wa.resume)
    assert not late.resumed


def test_bye_and_server_closes_leave_at_once_and_non_resumable_clients_too() -> None:
    core = RelayCore()
    a, _, b = pair(core)
    a.send(Bye(reason="done"), 2.0)
    core.disconnect(a.conn, 2.0)
    core.tick(2.0)  # presence notices go out at the room's tick
    assert kinds(b.read(2.0)) == [PeerLeft]
    plain = Client(core, core.connect(3.0))
    plain.send(Hello(agent="plain"), 3.0)
    (w,) = [e for e in plain.read(3.0) if isinstance(e, Welcome)]
    assert w.resume is None
    plain.send(Join(room="lobby", streams=STREAMS, rate=10.0), 3.0)
    plain.read(3.0)
    core.tick(3.0)
    b.read(3.0)
    core.disconnect(plain.conn, 4.0)
    core.tick(4.0)
    assert kinds(b.read(4.0)) == [PeerLeft]


def test_a_resume_into_other_streams_is_a_new_join() -> None:
    core = RelayCore()
    a, wa, b = pair(core)
    core.disconnect(a.conn, 2.0)
    back, _ = hello(core, 3.0, resume=wa.resume)
    join(back, 3.0, streams=("head",))
    core.tick(3.0)  # presence notices go out at the room's tick
    got = kinds(b.read(3.0))
    assert got[:3] == [PeerStalled, PeerLeft, PeerJoined]


async def test_a_cut_connection_resumes_over_real_sockets() -> None:
    """A client whose TCP connection is cut reconnects with its token: its peer sees
    peer_stalled then peer_resumed, never peer_left, and its poses again."""
    async with running_server(ServerConfig(host="127.0.0.1", port=0)) as srv:
        url = f"ws://127.0.0.1:{srv.port}"
        watcher = await ClientConnection.open(url, room="r", streams=STREAMS, rate=20)
        a = await ClientConnection.connect(url, resumable=True)
        assert a.welcome is not None and a.welcome.resume
        joined = await a.join(room="r", streams=STREAMS, rate=20)
        a.ws.transport.abort()  # the network drops it
        b = await ClientConnection.connect(url, resume=a.welcome.resume)
        assert b.welcome is not None and b.welcome.resumed and b.welcome.user == a.welcome.user
        again = await b.join(room="r", streams=STREAMS, rate=20)
        assert again.streams == joined.streams
        ids = list(again.streams.values())
        await b.send(PoseUpdate.from_arrays(1, ids, np.full(3, b.clock()), POSE))
        seen: list[object] = []
        async with asyncio.timeout(10):
            while not any(
                isinstance(e, Snapshot) and b.welcome.user in e.entries["user"] for e in seen
            ):
                seen.append((await watcher.recv()).event)
        notices = [type(e) for e in seen if isinstance(e, PeerStalled | PeerResumed | PeerLeft)]
        assert notices == [PeerStalled, PeerResumed]
        await watcher.close()
        await b.close()


def test_a_parked_member_leaves_no_due_tick_behind() -> None:
    """While a member is parked its grid moves on: the next tick is in the future, so
    ticking the room ends (it looped for ever) and other rooms go on."""
    core = RelayCore()
    a, _, _ = pair(core)
    core.disconnect(a.conn, 1.2)  # dropped: parked
    core.tick(1.5)
    due = core.next_deadline()
    assert due is not None and due > 1.5
    room = core.rooms[next(iter(core.rooms))]
    assert all(m.next_due > 1.5 for m in room.members.values())
