"""Relays as one server over a real nats-server: ``RelayServer`` with ``cluster`` set.

Two (or three) relays on loopback share one NATS; real websocket clients join
one room through different nodes and see one room: each other's presence,
poses bit-exact, events in order, the owner's errors. Empty rooms are given
up and claimed anew; an owner that goes away sends its forwarded clients
elsewhere with 1012; an unreachable NATS is one clear error.
"""

from __future__ import annotations

import asyncio
import contextlib
import re
import time
from collections.abc import AsyncIterator, Callable
from functools import partial
from pathlib import Path

import numpy as np
import pytest
from conftest import needs_nats
from relaykit import HELLO, Bot, errors, frame, raw_connect, raw_join, settle, until_closed
from support import poll_until, running_server

from posecast.bench.procs import _scrape
from posecast.client.bot import BotConfig, run_bot
from posecast.client.connection import ClientConnection
from posecast.protocol import (
    PeerJoined,
    PeerLeft,
    PeerResumed,
    PeerStalled,
    PoseUpdate,
    Snapshot,
    UserEvent,
)
from posecast.recorder import info, load_streams
from posecast.server.app import RelayServer, ServerConfig
from posecast.server.auth import make_token
from posecast.server.cluster import USER_BLOCK, ClusterError
from posecast.server.node import MOVED

pytestmark = needs_nats


def url_of(srv: RelayServer) -> str:
    return f"ws://127.0.0.1:{srv.port}"


def node(nats_url: str, name: str, **extra: object) -> ServerConfig:
    # A short lease keeps the tests quick; upkeep runs every third of it.
    return ServerConfig(
        host="127.0.0.1", port=0, cluster=nats_url, node=name, cluster_lease=1.5, **extra
    )  # type: ignore[arg-type]


@contextlib.asynccontextmanager
async def nodes(nats_url: str, *names: str) -> AsyncIterator[list[RelayServer]]:
    async with contextlib.AsyncExitStack() as stack:
        servers = [
            await stack.enter_async_context(running_server(node(nats_url, n))) for n in names
        ]
        yield servers


async def metrics(srv: RelayServer) -> dict[str, float]:
    """A node's /metrics (fetched off the loop the node runs on)."""
    figures = await asyncio.to_thread(_scrape, srv.port or 0, 5.0)
    assert figures is not None
    return figures


def sees(bot: Bot, user: int) -> bool:
    return any(p.user == user for p in bot.of_type(PeerJoined))


def got_poses_of(bot: Bot, user: int, n: int = 1) -> bool:
    """``bot`` got ``n`` snapshots or more carrying poses of ``user``."""
    return sum(user in set(s.users.tolist()) for _, s in bot.snapshots) >= n


async def test_a_room_split_over_two_nodes_is_one_room(nats_url: str) -> None:
    async with nodes(nats_url, "a", "b") as (a, b):
        clock = a.clock
        here = await Bot.join(url_of(a), clock, room="lab", rate=20.0, seed=1)
        far = await Bot.join(url_of(b), clock, room="lab", rate=10.0, seed=2)
        # Each node gave its client an id of its own block.
        assert here.user // USER_BLOCK != far.user // USER_BLOCK
        assert a.cluster is not None and a.cluster.owns("lab")
        assert b.cluster is not None and not b.cluster.owns("lab")
        assert "lab" not in b.rooms  # the room's state is on its owner only
        async with here.running(), far.running():
            await settle(partial(sees, here, far.user))
            await settle(partial(sees, far, here.user))
            await settle(partial(got_poses_of, here, far.user))
            await settle(partial(got_poses_of, far, here.user))
            # Ten snapshots or more each way (at 10 and 20 Hz: a second's worth).
            await settle(partial(got_poses_of, here, far.user, 10), limit=60.0)
            await settle(partial(got_poses_of, far, here.user, 10), limit=60.0)
            # Poses through the other node arrive bit-exact, at the rate each asked.
            checked = 0
            for bot, other in ((here, far), (far, here)):
                for _, snap in bot.snapshots:
                    caps = snap.capture_times
                    for i, (user, sid) in enumerate(
                        zip(snap.users.tolist(), snap.streams.tolist(), strict=True)
                    ):
                        if user != other.user:
                            continue
                        tol = abs(caps[i] - snap.send_time) * 2**-23 + 1e-9
                        sent = other.sent[sid].find(float(caps[i]), tol)
                        assert sent is not None
                        np.testing.assert_array_equal(snap.poses[i], sent)
                        checked += 1
            assert checked > 20
            assert here.rate == 20.0 and far.rate == 10.0
            # Events reach the other node's member in order.
            for k in range(6):
                await here.conn.send(UserEvent(kind="button", payload={"k": k}))
            await settle(lambda: len(far.of_type(UserEvent)) == 6)
            assert [e.payload["k"] for e in far.of_type(UserEvent)] == list(range(6))
            assert (await metrics(a))["posecast_cluster_remote_members"] == 1
            assert (await metrics(a))["posecast_cluster_received_frames_total"] > 10
            assert (await metrics(b))["posecast_cluster_forwarded_clients"] == 1
            assert (await metrics(b))["posecast_cluster_forwarded_frames_total"] > 10
            await far.conn.close()
            await settle(lambda: bool(here.of_type(PeerLeft)))
            assert [p.user for p in here.of_type(PeerLeft)] == [far.user]
        await here.conn.close()


async def test_the_owner_s_rules_hold_for_a_member_on_another_node(nats_url: str) -> None:
    """A frame the owner refuses: the member through another node gets the owner's
    error and close code, and the room's other member stays."""
    async with nodes(nats_url, "a", "b") as (a, b):
        here = await Bot.join(url_of(a), a.clock, room="lab", rate=10.0)
        ws = await raw_connect(url_of(b))
        user, _ = await raw_join(ws, "lab")
        assert a.cluster is not None and user in {m.user for m in a.rooms["lab"].members.values()}
        await ws.send(b"\x00not msgpack")
        messages, code = await until_closed(ws)
        assert code == 1002
        assert [e.code for e in errors(messages)] == ["bad-frame"]
        await settle(lambda: len(a.rooms["lab"].members) == 1)
        assert not here.conn.session.closed
        await here.conn.close()


async def test_an_empty_room_is_given_up_and_claimed_by_the_next_joiner(nats_url: str) -> None:
    async with nodes(nats_url, "a", "b") as (a, b):
        assert a.cluster is not None and b.cluster is not None
        first = await Bot.join(url_of(a), a.clock, room="lab", rate=10.0)
        assert a.cluster.owns("lab")
        await first.conn.close()
        await settle(lambda: not a.cluster.owns("lab"), limit=10.0)  # type: ignore[union-attr]
        second = await Bot.join(url_of(b), b.clock, room="lab", rate=10.0)
        assert b.cluster.owns("lab") and "lab" in b.rooms
        await second.conn.close()


async def test_clients_of_a_gone_owner_are_sent_to_reconnect(nats_url: str) -> None:
    async with running_server(node(nats_url, "b")) as b:
        async with running_server(node(nats_url, "a")) as a:
            owner = await Bot.join(url_of(a), a.clock, room="lab", rate=10.0)
            far = await Bot.join(url_of(b), b.clock, room="lab", rate=10.0)
            assert a.cluster is not None and a.cluster.owns("lab")
            async with far.running(publish=False):
                await settle(partial(sees, far, owner.user))
                a.stop()  # the owner goes; its client here goes with it
                with contextlib.suppress(Exception):
                    await owner.conn.close()
                await settle(lambda: far.closed is not None, limit=10.0)
        assert far.closed is not None and far.closed.rcvd is not None
        assert (far.closed.rcvd.code, far.closed.rcvd.reason) == MOVED
        # It joins again through the same node, which owns the room now.
        again = await Bot.join(url_of(b), b.clock, room="lab", rate=10.0)
        assert b.cluster is not None and b.cluster.owns("lab")
        await again.conn.close()


async def test_an_unreachable_nats_is_one_clear_error() -> None:
    server = RelayServer(ServerConfig(host="127.0.0.1", port=0, cluster="nats://127.0.0.1:1"))
    with pytest.raises(ClusterError, match=re.escape("cannot reach NATS at nats://127.0.0.1:1")):
        await server.run()


async def test_two_live_nodes_cannot_share_a_name(nats_url: str) -> None:
    async with running_server(node(nats_url, "a")):
        with pytest.raises(ClusterError, match="a live node is named 'a'"):
            await RelayServer(node(nats_url, "a")).run()


@pytest.mark.parametrize("codec", ["raw", "compact"])
async def test_a_split_room_has_one_recording_on_its_owner(
    nats_url: str, tmp_path: Path, codec: str
) -> None:
    """Four bots, two through each of two recording nodes: one file, on the room's
    owner, with every keyframe any bot received, bit-exact; the other node records
    nothing."""
    dirs = {name: tmp_path / name for name in ("a", "b")}
    async with contextlib.AsyncExitStack() as stack:
        servers = [
            # A join waits for its room's recorder process to start (seconds on a busy
            # machine): a keepalive of 2.5 s closed the joining bots meanwhile (1011).
            await stack.enter_async_context(
                running_server(node(nats_url, n, record_dir=d, ping_timeout=30.0))
            )
            for n, d in dirs.items()
        ]
        async with asyncio.TaskGroup() as tg:
            tasks = [
                tg.create_task(
                    run_bot(
                        BotConfig(
                            url=url_of(servers[i % 2]),
                            room="rec",
                            rate=20,
                            motion="synthetic:orbit",
                            seed=i,
                            duration=3.0,
                            methods=("soa",),
                            codec=codec,
                        )
                    )
                )
                for i in range(4)
            ]
    files = {name: sorted(d.glob("*.mcap")) for name, d in dirs.items()}
    assert sorted(len(f) for f in files.values()) == [0, 1], files
    (path,) = [f for fs in files.values() for f in fs]
    assert len(info(path)["users"]) == 4
    streams = load_streams(path)
    time_tol = 1e-5 if codec == "raw" else 1.0e-3 + 1e-6
    checked = 0
    for report in (t.result() for t in tasks):
        assert len(report.streams) == 9  # three peers, three streams each
        for key, received in report.streams.items():
            rec = streams[key]
            for cap, pose in zip(received.capture, received.poses, strict=True):
                i = int(np.argmin(np.abs(rec.times - cap)))
                assert abs(rec.times[i] - cap) < time_tol
                assert rec.poses[i].tobytes() == np.asarray(pose, dtype=np.float32).tobytes()
                checked += 1
    assert checked >= 4 * 9 * 2


STREAMS = ("head", "left", "right")
POSE = np.repeat(np.array([[0.0, 1.6, 0.0, 1.0, 0.0, 0.0, 0.0]]), 3, axis=0)


async def _resume_at(
    url: str, token: str, streams: dict[str, int], clock: Callable[[], float]
) -> ClientConnection:
    """Reconnect with ``token``: resumed as the same user, with the same stream ids."""
    back = await ClientConnection.connect(url, resume=token, clock=clock)
    assert back.welcome is not None and back.welcome.resumed
    again = await back.join(room="lab", streams=STREAMS, rate=20)
    assert again.streams == streams
    return back


async def _notices_until_poses_of(watcher: ClientConnection, user: int) -> list[type]:
    """Presence notices the watcher gets until a snapshot carries ``user``'s poses."""
    seen: list[object] = []
    async with asyncio.timeout(15):
        while not any(isinstance(e, Snapshot) and user in e.entries["user"] for e in seen):
            seen.append((await watcher.recv()).event)
    return [type(e) for e in seen if isinstance(e, PeerStalled | PeerResumed | PeerLeft)]


@pytest.mark.parametrize("back_through", ["same node", "other node"])
async def test_a_dropped_member_resumes_through_any_node(nats_url: str, back_through: str) -> None:
    """A member that came through node b (its room is a's) drops and resumes, through
    b again or through a: the same user and streams; the room's other member sees
    peer_stalled then peer_resumed, never peer_left."""
    async with nodes(nats_url, "a", "b") as (a, b):
        assert a.cluster is not None and b.cluster is not None
        clock = a.clock  # the cluster's time (the nodes' clocks are anchored to the wall)
        watcher = await ClientConnection.open(
            url_of(a), room="lab", streams=STREAMS, rate=20, clock=clock
        )
        x = await ClientConnection.connect(url_of(b), resumable=True, clock=clock)
        assert x.welcome is not None and x.welcome.resume
        joined = await x.join(room="lab", streams=STREAMS, rate=20)
        token = x.welcome.resume
        await settle(lambda: len(a.rooms["lab"].members) == 2)
        x.ws.transport.abort()  # the network drops it
        await settle(lambda: any(m.parked for m in a.rooms["lab"].members.values()))
        # The owner keeps the member's record in NATS, for a resume through any node.
        cluster = b.cluster

        async def recorded() -> bool:
            return await cluster.lookup(token) is not None

        await poll_until(recorded, limit=30.0, every=0.1)
        url = url_of(b) if back_through == "same node" else url_of(a)
        back = await _resume_at(url, token, joined.streams, clock)
        assert back.welcome is not None and back.welcome.user == x.welcome.user
        ids = list(joined.streams.values())
        await back.send(PoseUpdate.from_arrays(1, ids, np.full(3, back.clock()), POSE))
        notices = await _notices_until_poses_of(watcher, back.welcome.user)
        assert notices == [PeerStalled, PeerResumed]
        await watcher.close()
        await back.close()


async def test_tokens_are_checked_for_a_member_on_another_node(nats_url: str) -> None:
    """With a secret on every node, a join through another node needs a token for
    its room, as on one server; a refused one claims no room anywhere."""
    secret = "cluster test secret"
    async with contextlib.AsyncExitStack() as stack:
        a, b = [
            await stack.enter_async_context(running_server(node(nats_url, n, secret=secret)))
            for n in ("a", "b")
        ]
        assert a.cluster is not None and b.cluster is not None
        good = make_token(secret, "lab", "alice", ttl=60.0, now=time.time())
        first = await ClientConnection.open(
            url_of(a), room="lab", streams=STREAMS, rate=20, token=good, clock=a.clock
        )
        bob = make_token(secret, "lab", "bob", ttl=60.0, now=time.time())
        ok = await ClientConnection.open(
            url_of(b), room="lab", streams=STREAMS, rate=20, token=bob, clock=a.clock
        )
        assert ok.joined is not None and "lab" in a.rooms and len(a.rooms["lab"].members) == 2
        other = make_token(secret, "other", "mallory", ttl=60.0, now=time.time())
        ws = await raw_connect(url_of(b))
        await ws.send(HELLO)
        await ws.recv()
        await ws.send(frame("join", room="vault", streams=["head"], rate=10.0, token=other))
        messages, _ = await until_closed(ws, limit=3.0)
        assert "unauthorized" in [e.code for e in errors(messages)]
        assert await b.cluster.directory.owner("vault") is None
        await first.close()
        await ok.close()


async def test_a_node_stops_though_a_nats_reply_swallowed_its_cancellation(nats_url: str) -> None:
    """nats-py waits for its replies with ``asyncio.wait_for``, which on Python 3.11
    returns a reply that arrives together with a cancellation and drops the
    cancellation. A node stopped while its upkeep round waits on NATS must stop all
    the same: its upkeep ran on instead, its TaskGroup never ended, and a full suite
    hung in the teardown of two nodes, one listener open, both NATS connections up.

    The race is made certain here: the round's first NATS round trip is answered
    exactly when the node is stopped (a reply returned in place of the cancellation,
    as ``wait_for`` does). A hang guard cancels a still-running upkeep once more after
    30 s, so a regression fails instead of hanging."""
    loop = asyncio.get_running_loop()
    waiting, swallowed, stuck = asyncio.Event(), asyncio.Event(), []

    def unstick() -> None:  # the hang guard (no timing is checked)
        for task in asyncio.all_tasks():
            if task.get_name() == "cluster-upkeep" and not task.done():
                stuck.append(task.get_name())
                task.cancel()

    async with running_server(node(nats_url, "a")) as a:
        assert a.cluster is not None
        nc = a.cluster.directory.nc
        real_rtt = nc.rtt

        async def rtt(**kwargs: int) -> float:
            if swallowed.is_set() or waiting.is_set():
                return float(await real_rtt(**kwargs))
            waiting.set()
            try:
                await asyncio.Event().wait()  # the pong: it comes with the cancellation
            except asyncio.CancelledError:
                swallowed.set()
            return 0.0

        nc.rtt = rtt
        async with asyncio.timeout(30):  # (a hang guard)
            await waiting.wait()  # an upkeep round waits on NATS now
        guard = loop.call_later(30.0, unstick)
    guard.cancel()
    assert swallowed.is_set()
    assert stuck == [], "the upkeep ran on after it was cancelled"
