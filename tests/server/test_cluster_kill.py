"""Node loss for real: relay processes on one nats-server, the room's owner SIGKILLed.

The room's members resume on a live node with their user and stream ids: the
one that came through the surviving node is told to reconnect (1012) and
resumes there; the one whose socket was on the killed node reconnects to the
other node and resumes too. Neither sees the other leave.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager, suppress
from pathlib import Path

import numpy as np
from conftest import needs_nats
from relaykit import settle
from support import Pacer, poll_until
from websockets.exceptions import ConnectionClosed

from posecast.client.connection import ClientConnection
from posecast.cluster_local import RelayProcess, start_relay
from posecast.protocol import PeerLeft, PeerResumed, PoseUpdate, Snapshot
from posecast.recorder import find_leftovers, info, load_streams, recover
from posecast.server.cluster import Directory, member_key
from posecast.server.node import MOVED

pytestmark = needs_nats

STREAMS = ("head", "left", "right")
POSE = np.repeat(np.array([[0.0, 1.6, 0.0, 1.0, 0.0, 0.0, 0.0]]), 3, axis=0)


def cluster_time() -> float:
    """The nodes' clock (monotonic anchored to the wall clock: the wall clock's time)."""
    return time.time()


@asynccontextmanager
async def relay(nats_url: str, name: str, record: Path) -> AsyncIterator[RelayProcess]:
    """``posecast serve --cluster --record`` as its own process, stopped after."""
    node = await start_relay(nats_url, name, record_dir=record / name)
    try:
        yield node
    finally:
        await node.stop()


async def _publish_and_watch(
    conn: ClientConnection, stop: asyncio.Event, seen: list[object]
) -> None:
    """Publish 20 Hz until ``stop`` or the connection ends; what it receives into ``seen``."""
    assert conn.joined is not None
    ids = list(conn.joined.streams.values())

    async def read() -> None:
        with suppress(ConnectionClosed):
            while True:
                seen.append((await conn.recv()).event)

    async with asyncio.TaskGroup() as tg:
        reader = tg.create_task(read())
        seq = 0
        pacer = Pacer(0.05)
        with suppress(ConnectionClosed):
            while not stop.is_set() and not reader.done():
                seq += 1
                t = cluster_time()
                await conn.send(PoseUpdate.from_arrays(seq, ids, np.full(3, t), POSE))
                await pacer.next()
        reader.cancel()


async def _resume(urls: list[str], token: str, streams: dict[str, int]) -> ClientConnection:
    """What a bot does after a drop: try each node with its token until resumed."""
    resumed: list[ClientConnection] = []

    async def attempt() -> bool:
        for url in urls:
            with suppress(OSError, ConnectionClosed, TimeoutError):
                conn = await ClientConnection.connect(url, resume=token, clock=cluster_time)
                assert conn.welcome is not None and conn.welcome.resumed, conn.welcome
                joined = await conn.join(room="lab", streams=STREAMS, rate=20)
                assert joined.streams == streams
                resumed.append(conn)
                return True
        return False

    await poll_until(attempt, limit=20.0, every=0.2)
    return resumed[0]


async def _recorded(nats_url: str, tokens: list[str]) -> None:
    """Wait until NATS holds the member records of ``tokens`` in room lab."""
    probe = await Directory.open(nats_url, "probe")
    try:

        async def there() -> bool:
            keys = await probe.values(member_key("lab"))
            return all(member_key("lab", t) in keys for t in tokens)

        await poll_until(there, limit=30.0, every=0.1)
    finally:
        await probe.close()


async def test_members_of_a_killed_owner_resume_on_a_live_node(
    nats_url: str, tmp_path: Path
) -> None:
    """...and the room's recording goes on in a file on the new owner that names the
    lost node's; the lost node's file, recovered, holds the poses up to the kill but
    for the last second at most."""
    async with (
        relay(nats_url, "a", tmp_path) as owner,
        relay(nats_url, "b", tmp_path) as other,
    ):
        url_a, url_b = owner.url, other.url
        # The first joiner's node owns the room: x through a, y through b.
        x = await ClientConnection.connect(url_a, resumable=True, clock=cluster_time)
        joined_x = await x.join(room="lab", streams=STREAMS, rate=20)
        y = await ClientConnection.connect(url_b, resumable=True, clock=cluster_time)
        joined_y = await y.join(room="lab", streams=STREAMS, rate=20)
        assert x.welcome is not None and y.welcome is not None
        assert x.welcome.resume and y.welcome.resume
        stop = asyncio.Event()
        before: list[object] = []
        async with asyncio.TaskGroup() as tg:
            tg.create_task(_publish_and_watch(y, stop, before))
            seen_by_x: list[object] = []
            tg.create_task(_publish_and_watch(x, stop, seen_by_x))
            # The owner's member records reach NATS (every 0.25 s): seen there.
            await _recorded(nats_url, [x.welcome.resume, y.welcome.resume])
            # Each member's poses went through the owner (its recorder) for over a
            # second: what the lost node's file must keep (all but its last second).
            await settle(lambda: _span(before, x.welcome.user) > 1.5, limit=60.0)
            await settle(lambda: _span(seen_by_x, y.welcome.user) > 1.5, limit=60.0)
            killed_at, killed_time = time.monotonic(), cluster_time()
            owner.kill()
            await owner.proc.wait()
            # y's node finds the owner gone and tells y to reconnect (the task ends).
        assert y.ws.close_code == MOVED[0], y.ws.close_code
        moved_after = time.monotonic() - killed_at
        y2 = await _resume([url_b], y.welcome.resume, joined_y.streams)
        x2 = await _resume([url_a, url_b], x.welcome.resume, joined_x.streams)
        resumed_after = time.monotonic() - killed_at
        assert y2.welcome is not None and y2.welcome.user == y.welcome.user
        assert x2.welcome is not None and x2.welcome.user == x.welcome.user
        after: list[object] = []
        async with asyncio.TaskGroup() as tg:
            tg.create_task(_publish_and_watch(y2, stop, after))
            tg.create_task(_publish_and_watch(x2, stop, []))
            user = x.welcome.user
            await settle(lambda: any(_carries(e, user) for e in after), limit=15.0)
            stop.set()
        assert any(_carries(e, x.welcome.user) for e in before)
        assert not [e for e in before + after if isinstance(e, PeerLeft)]
        assert any(isinstance(e, PeerResumed) and e.user == x.welcome.user for e in after)
        print(
            f"\nkill drill: y told to reconnect {moved_after:.2f} s after the SIGKILL; "
            f"both resumed {resumed_after:.2f} s after it"
        )
        await x2.close()
        await y2.close()
    # b stopped (SIGTERM): its file is finished; a's was cut by the kill.
    (moved,) = (tmp_path / "b").glob("*.mcap")
    summary = info(moved)
    assert summary["cluster_node"] == "b" and summary["continues_from_node"] == "a"
    assert {u["user"] for u in summary["users"]} == {x.welcome.user, y.welcome.user}
    (report,) = recover_all(tmp_path / "a")
    lost = info(report)
    assert lost["cluster_node"] == "a" and lost["continues_from_node"] is None
    streams = load_streams(report)
    assert {user for user, _ in streams} == {x.welcome.user, y.welcome.user}
    last = max(float(s.times.max()) for s in streams.values())
    # (printed, not asserted: how much of the tail the kill took depends on the load)
    print(f"the lost node's recording ends {killed_time - last:.2f} s before the kill")


def _span(seen: list[object], user: int) -> float:
    """Seconds of ``user``'s capture times among the snapshots in ``seen``."""
    caps = [
        float(t)
        for e in seen
        if isinstance(e, Snapshot)
        for u, t in zip(e.users.tolist(), e.capture_times.tolist(), strict=True)
        if u == user
    ]
    return max(caps) - min(caps) if caps else 0.0


def _carries(event: object, user: int) -> bool:
    return isinstance(event, Snapshot) and user in event.entries["user"]


def recover_all(folder: Path) -> list[Path]:
    """Recover the unfinished recordings a killed node left in ``folder``."""
    return [recover(part).output for part in find_leftovers(folder)]
