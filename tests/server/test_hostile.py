"""Hostile clients against the real relay: each gets a clear error and/or close code,
its bad data never reaches anyone, and well-behaved members keep their rates.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import sys
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
import relaykit
from relaykit import (
    EXPECTED_CLOSE,
    FATAL,
    GOOD,
    HELLO,
    Bot,
    DueTicks,
    barrier,
    close_reason,
    errors,
    flowing,
    frame,
    join_frame,
    joined_raw,
    keyframe_rates,
    keyframe_window,
    keyframes_per_tick,
    never_reader,
    raw_connect,
    settle,
    until_closed,
    update_bytes,
    window_full,
)
from support import poll_until
from websockets.asyncio.client import ClientConnection as WsConnection
from websockets.exceptions import ConnectionClosed

from posecast.protocol import PeerJoined, PeerLeft, UserEvent
from posecast.server.app import RelayServer, ServerConfig

ServerFactory = Callable[..., Any]


def url_of(srv: RelayServer) -> str:
    return f"ws://127.0.0.1:{srv.port}"


def update_frame(
    srv: RelayServer, streams: list[int], poses: np.ndarray | list[list[float]], seq: int = 0
) -> bytes:
    return update_bytes(streams, poses, seq, srv.clock())


def metric(srv: RelayServer, name: str) -> float:
    for line in srv.metrics_text().splitlines():
        if line.split(" ")[0] == name:
            return float(line.split(" ")[1])
    raise KeyError(name)


@contextlib.asynccontextmanager
async def observed_room(srv: RelayServer, room: str = "r") -> AsyncIterator[Bot]:
    """A well-behaved bot publishing at 30 Hz and subscribed at 20 Hz in ``room``."""
    bot = await Bot.join(url_of(srv), srv.clock, room=room, rate=20.0, seed=11)
    async with bot.running():
        yield bot
    await bot.conn.close()


async def joined_ws(srv: RelayServer, room: str = "r") -> tuple[WsConnection, list[int]]:
    ws, _, ids = await joined_raw(url_of(srv), room)
    return ws, ids


async def joined_user(srv: RelayServer, room: str = "r") -> tuple[WsConnection, int, list[int]]:
    return await joined_raw(url_of(srv), room)


# -- fatal attacks: error message (when the server can still speak) and close code ----


@pytest.mark.parametrize("name", list(FATAL))
async def test_fatal_attack_closes_only_the_attacker(
    server_factory: ServerFactory, name: str
) -> None:
    """A joined client breaking the protocol gets the error code and close code; peers go on."""
    attack, code, close = FATAL[name]
    async with server_factory() as srv, observed_room(srv) as bot:
        ws, _ = await joined_ws(srv)
        # Presence goes out per tick: a join and a leave within one would be no news.
        await settle(lambda: bool(bot.of_type(PeerJoined)))
        await attack(ws)
        got, close_code = await until_closed(ws)
        assert close_code == close
        assert [e.code for e in errors(got)] == ([code] if code else [])
        assert all(e.fatal for e in errors(got))
        # The room saw the attacker leave and keeps streaming to the others.
        await settle(lambda: bool(bot.of_type(PeerLeft)))
        # A newcomer's join right after must not trip over the closed session.
        late = await Bot.join(url_of(srv), srv.clock, room="r", rate=10.0)
        async with late.running(publish=False):
            n = len(bot.snapshots)
            await settle(lambda: len(bot.snapshots) >= n + 5 and len(late.snapshots) >= 2)
        await late.conn.close()
        assert bot.closed is None


async def test_message_before_hello_refused(server_factory: ServerFactory) -> None:
    """A join before hello gets "unexpected-message" and close 1002."""
    async with server_factory() as srv:
        ws = await raw_connect(url_of(srv))
        await ws.send(join_frame("r"))
        got, close_code = await until_closed(ws)
        assert close_code == 1002
        assert [(e.code, e.message) for e in errors(got)] == [
            ("unexpected-message", "join before hello")
        ]


async def test_garbage_before_hello_refused(server_factory: ServerFactory) -> None:
    """Garbage as the very first frame gets "bad-frame" and close 1002."""
    async with server_factory() as srv:
        ws = await raw_connect(url_of(srv))
        await ws.send(b"\x00\x01\x02")
        got, close_code = await until_closed(ws)
        assert close_code == 1002
        assert [e.code for e in errors(got)] == ["bad-frame"]


async def test_spoofed_stream_refused_and_not_relayed(server_factory: ServerFactory) -> None:
    """An update naming another user's stream: "stream-not-owned", close 1008, never relayed."""
    async with server_factory() as srv, observed_room(srv) as bot:
        ws, _ = await joined_ws(srv)
        victim = bot.stream_ids[0]
        spoof = [[666.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]]
        await ws.send(update_frame(srv, [victim], spoof))
        got, close_code = await until_closed(ws)
        assert close_code == 1008
        assert [(e.code, e.fatal) for e in errors(got)] == [("stream-not-owned", True)]
        n = len(bot.snapshots)
        await settle(lambda: len(bot.snapshots) >= n + 3)
    assert not any((snap.poses[:, 0] == 666.0).any() for _, snap in bot.snapshots)


@pytest.mark.parametrize(
    "pose",
    [
        pytest.param([0.0, float("nan"), 0.0, 1.0, 0.0, 0.0, 0.0], id="nan"),
        pytest.param([float("inf"), 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], id="inf"),
        pytest.param([0.0, 0.0, 0.0, 1.01, 0.0, 0.0, 0.0], id="quaternion norm 1.01"),
        pytest.param([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], id="zero quaternion"),
    ],
)
async def test_bad_pose_dropped_connection_kept(
    server_factory: ServerFactory, pose: list[float]
) -> None:
    """A bad pose gets a non-fatal "bad-pose" error and is dropped; later good ones flow."""
    async with server_factory() as srv, observed_room(srv) as bot:
        ws, ids = await joined_ws(srv)
        bad = [pose, [7.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]]  # one bad pose spoils the update
        await ws.send(update_frame(srv, ids, bad, seq=0))
        reply = msgpack.unpackb(await asyncio.wait_for(ws.recv(), 10))
        while reply["type"] != "error":  # snapshots and peer notices may come first
            reply = msgpack.unpackb(await asyncio.wait_for(ws.recv(), 10))
        assert (reply["code"], reply["fatal"], reply["in_reply_to"]) == (
            "bad-pose",
            False,
            "update",
        )
        await ws.send(update_frame(srv, ids, [[8.0, 0, 0, 1, 0, 0, 0]] * 2, seq=1))
        await settle(lambda: any((snap.poses[:, 0] == 8.0).any() for _, snap in bot.snapshots))
        await ws.close()
    for _, snap in bot.snapshots:
        assert np.isfinite(snap.poses).all()
        assert not (snap.poses[:, 0] == 7.0).any()


async def test_bad_rate_join_refused_then_retry(server_factory: ServerFactory) -> None:
    """A join asking 100 Hz gets a non-fatal "bad-rate" refusal; a proper join then works."""
    async with server_factory() as srv:
        ws = await raw_connect(url_of(srv))
        await ws.send(HELLO)
        await ws.recv()
        await ws.send(join_frame("r", rate=100.0))
        reply = msgpack.unpackb(await asyncio.wait_for(ws.recv(), 10))
        assert (reply["type"], reply["code"], reply["fatal"], reply["in_reply_to"]) == (
            "error",
            "bad-rate",
            False,
            "join",
        )
        await ws.send(join_frame("r", rate=10.0))
        assert msgpack.unpackb(await asyncio.wait_for(ws.recv(), 10))["type"] == "joined"
        await ws.close()


# -- floods -----------------------------------------------------------------------------


async def test_update_flood_dropped_counted_then_closed(server_factory: ServerFactory) -> None:
    """Updates beyond max_update_rate are dropped and counted; a long flood is closed 1008."""
    cfg = ServerConfig(host="127.0.0.1", port=0, max_update_rate=60.0)
    async with server_factory(cfg) as srv, observed_room(srv) as bot:
        start = srv.clock()
        ws, user, ids = await joined_user(srv)
        member = srv.rooms["r"].members[user]
        with contextlib.suppress(ConnectionClosed):
            for seq in range(5000):
                await ws.send(update_frame(srv, ids, [GOOD[0]] * 2, seq=seq))
                if seq % 50 == 0:
                    await asyncio.sleep(0)
        _, close_code = await until_closed(ws)
        elapsed = srv.clock() - start
        assert close_code == 1008
        assert "flood" in (close_reason(ws) or "")
        # What got through respects the bucket: one second's burst plus the refill.
        assert 0 < member.updates_in <= 60.0 * (1.0 + elapsed)
        assert metric(srv, "posecast_flood_drops_total") >= 10 * 60.0
        assert bot.closed is None


async def test_event_flood_is_rate_limited(server_factory: ServerFactory) -> None:
    """A burst of user events is capped like updates: peers never get more than the bucket."""
    cfg = ServerConfig(host="127.0.0.1", port=0, max_update_rate=60.0)
    async with server_factory(cfg) as srv, observed_room(srv) as bot:
        ws, ids = await joined_ws(srv)
        start = srv.clock()
        with contextlib.suppress(ConnectionClosed):
            for k in range(3000):
                await ws.send(frame("event", kind="button", stream=ids[0], payload={"k": k}))
                if k % 50 == 0:
                    await asyncio.sleep(0)
        _, close_code = await until_closed(ws)
        elapsed = srv.clock() - start
        assert close_code == 1008
        await barrier(bot)  # every event the relay passed on has arrived
        assert 0 < len(bot.of_type(UserEvent)) <= 60.0 * (1.0 + elapsed)
        assert bot.closed is None


# -- a client that never reads -------------------------------------------------------------


BIG = ("head", "left", "right", *(f"object:o{i}" for i in range(13)))


async def test_never_reading_client_bounded_and_harmless(server_factory: ServerFactory) -> None:
    """A client that stops reading: bounded memory, skips counted, others' rates kept, 1008."""
    # Well-behaved rates are compared with a run before it joined (within 10 %);
    # its event queue overflow must close it without waiting for it to read.
    cfg = ServerConfig(host="127.0.0.1", port=0, max_event_queue=16, close_timeout=0.5)
    async with server_factory(cfg) as srv:
        url, clock = url_of(srv), srv.clock
        pubs = [
            await Bot.join(url, clock, room="r", rate=rate, streams=BIG, seed=i)
            for i, rate in enumerate((10.0, 20.0, 20.0))
        ]
        async with contextlib.AsyncExitStack() as stack:
            for bot in pubs:
                await stack.enter_async_context(bot.running())
            await flowing(pubs)
            t0, t1 = await keyframe_window(pubs, 2.0, clock)
            ws, user = await never_reader(srv, "r")
            conn = srv.connection_of(user)
            await settle(lambda: conn.outbox.skips >= 5)
            peak_buffer = 0
            queued: list[int] = []

            def sample() -> None:
                # Latest wins: at most one snapshot waits, the queue stays bounded.
                nonlocal peak_buffer
                queued.append(len(conn.outbox.events))
                peak_buffer = max(peak_buffer, conn.ws.transport.get_write_buffer_size())

            # Sampled all along a window of two seconds of keyframes while it is stuck.
            t2 = clock()
            await poll_until(lambda: sample() or window_full(pubs, t2, 2.0), every=0.05)
            t3 = clock()
            assert queued and max(queued) <= cfg.max_event_queue
            skips = conn.outbox.skips
            assert skips > 10
            assert metric(srv, "posecast_snapshot_skips_total") >= skips
            assert peak_buffer <= cfg.congested_bytes + 2 * 1024
            # Reliable traffic to it overflows its queue: closed, and promptly gone.
            for k in range(cfg.max_event_queue + 4):
                await pubs[0].conn.send(UserEvent(kind="button", payload={"k": k}))
            await settle(lambda: user not in srv.rooms["r"].members)
            await settle(lambda: all(b.of_type(PeerLeft) for b in pubs[1:]))
            await settle(lambda: metric(srv, "posecast_connections") == len(pubs))
        for bot in pubs:
            assert bot.closed is None
            remote = {(b.user, s) for b in pubs if b is not bot for s in b.stream_ids}
            base = keyframe_rates(bot.snapshots, t0, t1)
            hit = keyframe_rates(bot.snapshots, t2, t3)
            for key in remote:
                assert base[key] == pytest.approx(bot.rate, rel=0.1)
                assert hit.get(key, 0.0) == pytest.approx(base[key], rel=0.1), (key, base, hit)
            await bot.conn.close()
        ws.transport.abort()


# -- everything at once, against the rates of well-behaved members --------------------------


async def test_rates_unaffected_by_attackers(server_factory: ServerFactory) -> None:
    """While hostile clients cycle through every attack, subscribers keep their rates: a new
    keyframe of every remote stream at each of their ticks, as before the attacks (10 %)."""
    # The attackers run in their own process, as they would in real life; a
    # client that never reads sits in the room all along.
    async with server_factory() as srv:
        url, clock = url_of(srv), srv.clock
        bots = [
            await Bot.join(url, clock, room="r", rate=rate, streams=BIG, seed=i)
            for i, rate in enumerate((10.0, 20.0, 15.0))
        ]
        due = DueTicks(srv.rooms["r"], [bot.user for bot in bots])
        async with contextlib.AsyncExitStack() as stack:
            for bot in bots:
                await stack.enter_async_context(bot.running())
            await flowing(bots)
            t0, t1 = await keyframe_window(bots, 2.5, clock)
            stuck, _ = await never_reader(srv, "r")
            await settle(lambda: metric(srv, "posecast_snapshot_skips_total") > 0)
            victim = str(bots[0].stream_ids[0])
            proc = await asyncio.create_subprocess_exec(
                sys.executable, relaykit.__file__, url, "r", victim, "120",
                stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE,
                env={**os.environ, "PYTHONPATH": str(Path(__file__).parent.parent)},
            )  # fmt: skip
            assert proc.stdout is not None and proc.stdin is not None
            async with asyncio.timeout(30):
                assert await proc.stdout.readline() == b"attacking\n"
            t2, t3 = await keyframe_window(bots, 2.5, clock)
            proc.stdin.close()  # the attacks stop after this round
            async with asyncio.timeout(60):
                out, _ = await proc.communicate()
            stuck.transport.abort()
        assert proc.returncode == 0
        log = [(name, code) for name, code in json.loads(out)]
        assert {name for name, _ in log} >= {"spoof", "before hello", *list(FATAL)[:2]}
        assert all(code == EXPECTED_CLOSE[name] for name, code in log), log
        for bot in bots:
            assert bot.closed is None
            remote = {(b.user, s) for b in bots if b is not bot for s in b.stream_ids}
            # Per slot the relay reached, not per second (a loaded machine makes it
            # skip slots): each carries a new keyframe of every remote stream
            # (publishers send at 30 Hz, above every granted rate), attacks or not.
            base = keyframes_per_tick(bot, due, t0, t1)
            hit = keyframes_per_tick(bot, due, t2, t3)
            for key in remote:
                assert base[key] == pytest.approx(1.0, rel=0.1), (key, base)
                assert hit.get(key, 0.0) == pytest.approx(base[key], rel=0.1), (key, base, hit)
            await bot.conn.close()


async def test_a_connection_that_never_joins_is_closed_1008(
    server_factory: ServerFactory,
) -> None:
    """Hello and then nothing: closed 1008 "no join" at the join deadline; members go on."""
    cfg = ServerConfig(host="127.0.0.1", port=0, join_timeout=0.2)
    async with server_factory(cfg) as srv:
        member, _, _ = await joined_raw(url_of(srv), "r")
        idle = await raw_connect(url_of(srv))
        await idle.send(HELLO)
        got, code = await until_closed(idle)
        assert code == 1008 and close_reason(idle) == "no join within 0.2 s"
        assert errors(got) == [] and srv.core.join_timeouts == 1
        assert member.protocol.close_rcvd is None and len(srv.rooms["r"].members) == 1
        await member.close()


async def test_connections_per_address_are_limited(server_factory: ServerFactory) -> None:
    """Over max_connections_per_address: closed at once with 1013; a freed place is reused."""
    cfg = ServerConfig(host="127.0.0.1", port=0, max_connections_per_address=2)
    async with server_factory(cfg) as srv:
        first, _, _ = await joined_raw(url_of(srv), "r")
        second, _, _ = await joined_raw(url_of(srv), "r")
        third = await raw_connect(url_of(srv))
        _, code = await until_closed(third)
        assert code == 1013
        assert close_reason(third) == ("try again later: too many connections from one address (2)")
        await first.close()
        await settle(lambda: srv.closed_connections == 2)
        again, _, _ = await joined_raw(url_of(srv), "r")
        assert srv.core.refused_connections == 1 and len(srv.rooms["r"].members) == 2
        await again.close()
        await second.close()
