"""Presence notices batched per room tick (``server.presence``, issue 29).

The pure per-member queue first, then the sans-I/O core with fake times, then a
real relay on loopback whose clock the test holds still and steps, so that "one
batch per tick" is checked by tick control, never by wall-clock timing.
"""

from __future__ import annotations

import asyncio

from support import poll_until
from test_core import Client, connect

from posecast.client.connection import ClientConnection
from posecast.protocol import (
    Bye,
    Hello,
    Join,
    PeerJoined,
    PeerLeft,
    PeerStalled,
    Ping,
    Pong,
    UserEvent,
    Welcome,
)
from posecast.server.app import RelayServer, ServerConfig, serving
from posecast.server.core import RelayCore
from posecast.server.presence import PER_TICK, Presence

STREAMS = ("head", "left", "right")


def joined(user: int, sid: int = 0) -> PeerJoined:
    return PeerJoined(user=user, streams={"head": sid})


def left(user: int, reason: str = "left") -> PeerLeft:
    return PeerLeft(user=user, reason=reason)


def test_a_join_and_leave_within_a_tick_is_no_news() -> None:
    """A user announced to nobody yet who leaves again leaves nothing to send."""
    p = Presence()
    p.joined(joined(5))
    p.left(left(5))
    assert p.take() == [] and len(p) == 0


def test_repeated_changes_collapse_to_the_net_state() -> None:
    """Known user: leave, join, leave is one peer_left (the first reason); leave then
    join as a new member is peer_left then the newest peer_joined."""
    p = Presence()
    p.left(left(1, "left"))
    p.joined(joined(1, 10))
    p.left(left(1, "gone"))
    assert p.take() == [left(1, "left")]
    p.left(left(2))
    p.joined(joined(2, 20))
    p.left(left(2))
    p.joined(joined(2, 30))
    assert p.take() == [left(2), joined(2, 30)]
    assert p.take() == []


def test_departures_go_first_and_each_user_keeps_its_order() -> None:
    """Across users: every peer_left before any peer_joined; per user, left before joined."""
    p = Presence()
    p.joined(joined(7))
    p.left(left(3))
    p.joined(joined(3, 4))
    p.left(left(9))
    assert p.take() == [left(3), left(9), joined(7), joined(3, 4)]


def test_the_excess_carries_over_in_order() -> None:
    """Over the per-tick bound the rest waits for the next take, in the same order, and
    a user's arrival never overtakes its own departure."""
    p = Presence()
    for u in range(5):
        p.left(left(u))
    p.joined(joined(2, 50))  # 2 came back as a new member
    p.joined(joined(8))
    first = p.take(limit=3)
    assert first == [left(0), left(1), left(2)]
    second = p.take(limit=3)
    assert second == [left(3), left(4), joined(2, 50)]
    assert p.take(limit=3) == [joined(8)] and len(p) == 0


def test_a_users_own_notices_are_taken_alone() -> None:
    """take_user gives one user's pending notices (in order) and leaves the others."""
    p = Presence()
    p.left(left(4))
    p.joined(joined(4, 40))
    p.joined(joined(6))
    assert p.take_user(4) == [left(4), joined(4, 40)]
    assert p.take_user(4) == [] and p.take_user(None) == []
    assert p.take() == [joined(6)]


def _presence(events: list[object]) -> list[tuple[str, int]]:
    return [
        ("joined" if isinstance(e, PeerJoined) else "left", e.user)
        for e in events
        if isinstance(e, PeerJoined | PeerLeft)
    ]


def tick(core: RelayCore) -> float:
    """Run the next room tick; returns its time."""
    due = core.next_deadline()
    assert due is not None
    core.tick(due)
    return due


def test_core_sends_net_notices_once_per_tick() -> None:
    """N joins and leaves between two ticks: nothing until the tick, then the net change."""
    core = RelayCore()
    a = connect(core, 1.0)
    stay = connect(core, 1.0)
    t = tick(core)
    assert _presence(a.read(t)) == [("joined", stay.user)]
    for i in range(20):
        now = t + 0.001 * (i + 1)
        c = connect(core, now)
        core.disconnect(c.conn, now)
        assert _presence(a.read(now)) == []  # nothing between ticks
    core.disconnect(stay.conn, t + 0.03)
    late = connect(core, t + 0.031)
    assert _presence(a.read(t + 0.031)) == []
    t = tick(core)
    assert _presence(a.read(t)) == [("left", stay.user), ("joined", late.user)]
    t = tick(core)
    assert _presence(a.read(t)) == []


def test_news_of_a_peer_never_overtakes_its_peer_joined() -> None:
    """An event from a peer not announced yet flushes its peer_joined first."""
    core = RelayCore()
    a = connect(core, 1.0)
    t = tick(core)
    b = connect(core, t + 0.01)
    b.send(UserEvent(kind="button", stream=b.streams["head"], time=t + 0.01), t + 0.01)
    got = [e for e in a.read(t + 0.01) if isinstance(e, PeerJoined | UserEvent)]
    assert [type(e) for e in got] == [PeerJoined, UserEvent] and got[0].user == b.user
    t = tick(core)
    assert _presence(a.read(t)) == []  # announced once


def test_a_member_gets_at_most_per_tick_notices_per_tick() -> None:
    """More net changes than PER_TICK in one tick: the bound holds, the rest follows."""
    core = RelayCore(ServerConfig(max_members=PER_TICK + 10))
    a = connect(core, 1.0)
    t = tick(core)
    others = [connect(core, t + 0.01) for _ in range(PER_TICK + 5)]
    t = tick(core)
    first = _presence(a.read(t))
    t = tick(core)
    second = _presence(a.read(t))
    assert len(first) == PER_TICK and len(second) == 5
    assert first + second == [("joined", c.user) for c in others]


def test_a_resumed_member_is_not_told_twice() -> None:
    """A member that drops and resumes within one tick gets the room anew, no pending
    peer_joined on top (its peer list came with the resume)."""
    core = RelayCore()
    a = Client(core, core.connect(1.0))
    a.send(Hello(agent="r", resumable=True), 1.0)
    (w,) = [e for e in a.read(1.0) if isinstance(e, Welcome)]
    a.send(Join(room="lobby", streams=STREAMS, rate=10.0), 1.0)
    a.read(1.0)
    t = tick(core)
    b = connect(core, t + 0.01)  # a has b pending
    core.disconnect(a.conn, t + 0.02)
    back = Client(core, core.connect(t + 0.03))
    back.send(Hello(agent="r", resumable=True, resume=w.resume), t + 0.03)
    back.read(t + 0.03)
    back.send(Join(room="lobby", streams=STREAMS, rate=10.0), t + 0.03)
    t = tick(core)
    assert _presence(back.read(t)) == [("joined", b.user)]
    assert [e for e in b.read(t) if isinstance(e, PeerStalled)]


# -- over a real relay whose clock the test steps ------------------------------------


class SteppedClock:
    """The relay's clock: still until the test steps it (ticks happen only then)."""

    def __init__(self, now: float = 100.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


async def _barrier(conn: ClientConnection, got: list[object], seq: int) -> None:
    """Everything the relay queued for ``conn`` before this ping has arrived once its
    pong has (one reliable, ordered queue)."""
    await conn.send(Ping(seq=seq, time=0.0))
    while True:
        ev = (await conn.recv()).event
        if isinstance(ev, Pong) and ev.seq == seq:
            return
        got.append(ev)


async def _wait_members(srv: RelayServer, n: int) -> None:
    await poll_until(lambda: len(srv.core.rooms["r"].members) == n, limit=10.0, every=0.01)


async def test_churn_over_a_real_relay_gives_one_net_batch_per_tick() -> None:
    """Joins and leaves of real clients while the relay's clock stands still reach a
    member as nothing; stepping the clock past the room's tick delivers the net change
    (departures, then arrivals), once."""
    clock = SteppedClock()
    srv_cfg = ServerConfig(host="127.0.0.1", port=0)
    async with serving(RelayServer(srv_cfg, clock=clock)) as srv:
        url = f"ws://127.0.0.1:{srv.port}"
        watcher = await ClientConnection.open(url, room="r", streams=STREAMS, rate=20)
        got: list[object] = []
        stayer: ClientConnection | None = None
        seq = 0
        for step in range(4):
            churned = []
            for _ in range(5):
                c = await ClientConnection.open(url, room="r", streams=STREAMS, rate=20)
                churned.append(c.user)
                await c.send(Bye(reason="churn"))
                await c.close()
            gone = stayer
            if gone is not None:
                await gone.close()
            stayer = await ClientConnection.open(url, room="r", streams=STREAMS, rate=20)
            await _wait_members(srv, 2)
            seq += 1
            await _barrier(watcher, got, seq)
            assert _presence(got) == [], f"step {step}: presence before the tick"
            clock.now += 0.1  # past the room's next tick
            seq += 1
            await asyncio.wait_for(_barrier_after_tick(srv, watcher, got, seq), 10.0)
            want = ([("left", gone.user)] if gone is not None else []) + [("joined", stayer.user)]
            assert _presence(got) == want, f"step {step}"
            assert not set(churned) & {u for _, u in _presence(got)}
            got.clear()
        await stayer.close()
        await watcher.close()


async def _barrier_after_tick(
    srv: RelayServer, conn: ClientConnection, got: list[object], seq: int
) -> None:
    """Wait for the relay's ticker to run the room's tick at the stepped clock, then
    for everything queued before it (a ping barrier)."""
    room = srv.core.rooms["r"]
    await poll_until(lambda: (room.next_due() or 0.0) > srv.clock(), limit=10.0, every=0.01)
    await _barrier(conn, got, seq)
