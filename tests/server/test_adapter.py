"""The relay's asyncio adapter (``server/app.py``, ``server/transport.py``) on real sockets.

One ``asyncio.Protocol`` per websocket, no task and no Event per connection:
frames are built once per payload and written to every subscriber of it, a read
holding many frames is handled whole, writes wait while the transport's buffer
is full, each room ticks at its own clock reading into the tick lag histogram,
and the same relay runs on uvloop (what ``posecast serve`` uses).
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
from typing import Any

import msgpack
import pytest
import uvloop
from relaykit import (
    Bot,
    never_reader,
    raw_connect,
    raw_join,
    settle,
    until_closed,
    update_bytes,
)
from support import running_server
from test_core import connect
from test_http import http_get, parse_metrics
from websockets.frames import Frame, Opcode
from websockets.streams import StreamReader

import posecast.server.app as server_app
import posecast.server.connection as server_connection
from posecast.client.connection import ClientConnection
from posecast.protocol import PoseUpdate, Snapshot, UserEvent, encode_message
from posecast.server.app import ServerConfig
from posecast.server.core import TICK_LAG_BUCKETS, RelayCore
from posecast.server.http import metrics_text
from posecast.server.transport import frame_binary

POSE = [[0.5, 1.5, 0.0, 1.0, 0.0, 0.0, 0.0]]


def config(**kw: Any) -> ServerConfig:
    return ServerConfig(host="127.0.0.1", port=0, **kw)


def masked(payload: bytes, opcode: Opcode = Opcode.BINARY, fin: bool = True) -> bytes:
    """A client's (masked) frame, as websockets itself would send it."""
    return Frame(opcode, payload, fin=fin).serialize(mask=True, extensions=[])


@pytest.mark.parametrize("size", [0, 1, 125, 126, 65535, 65536, 70_000])
def test_frame_binary_is_what_websockets_parses(size: int) -> None:
    """Each length encoding (7-bit, 16-bit, 64-bit) parses back to the payload, FIN set."""
    payload = bytes(range(256)) * (size // 256) + bytes(size % 256)
    reader = StreamReader()
    reader.feed_data(frame_binary(payload))
    reader.feed_eof()
    parser = Frame.parse(reader.read_exact, mask=False)
    with pytest.raises(StopIteration) as done:
        next(parser)
    frame = done.value.value
    assert (frame.opcode, frame.fin, frame.data) == (Opcode.BINARY, True, payload)


async def test_subscribers_of_one_tick_group_share_one_frame(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Six subscribers at one rate get each snapshot from one framing, not six."""
    built: list[int] = []

    def counting(payload: bytes) -> bytes:
        built.append(len(payload))
        return frame_binary(payload)

    monkeypatch.setattr(server_connection, "frame_binary", counting)
    async with running_server(config()) as srv:
        url = f"ws://127.0.0.1:{srv.port}"
        pub = await Bot.join(url, srv.clock, room="g", rate=20.0, seed=1)
        subs = [
            await Bot.join(url, srv.clock, room="g", rate=20.0, streams=("head",), seed=2 + i)
            for i in range(6)
        ]
        async with contextlib.AsyncExitStack() as stack:
            await stack.enter_async_context(pub.running())
            for sub in subs:
                await stack.enter_async_context(sub.running(publish=False))
            await settle(lambda: all(len(s.snapshots) >= 3 for s in subs))
            before = len(built), sum(len(s.snapshots) for s in subs)
            await settle(lambda: all(len(s.snapshots) >= 13 for s in subs))
            framed = len(built) - before[0]
            delivered = sum(len(s.snapshots) for s in subs) - before[1]
        # Every snapshot framed served the six subscribers (plus the odd pong or
        # notice, framed alone); framing per subscriber would make these equal.
        assert delivered >= 60
        assert framed * 3 <= delivered, (framed, delivered)
        for bot in (pub, *subs):
            await bot.conn.close()


async def test_a_read_holding_many_frames_is_handled_whole() -> None:
    """Updates, a fragmented message and a ping sent in one write are all handled, in order."""
    async with running_server(config()) as srv:
        url = f"ws://127.0.0.1:{srv.port}"
        watcher = await Bot.join(url, srv.clock, room="r", rate=20.0, streams=("head",))
        ws = await raw_connect(url)
        user, streams = await raw_join(ws, "r", ("head",))
        sid = streams["head"]
        peer = srv.core.peer_of(user)
        frames_before = peer.frames_in
        now = srv.clock()
        ping = msgpack.packb({"type": "ping", "seq": 7, "time": now})
        updates = [
            update_bytes(
                [sid], [[0.1 * k, 1.5, 0.0, 1.0, 0.0, 0.0, 0.0]], seq=k, now=now + 0.001 * k
            )
            for k in range(1, 11)
        ]
        half = len(ping) // 2
        burst = [masked(u) for u in updates]
        burst += [masked(ping[:half], fin=False), masked(ping[half:], Opcode.CONT)]
        ws.transport.write(b"".join(burst))  # one write: one or very few reads
        async with watcher.running(publish=False):
            reply = msgpack.unpackb(await asyncio.wait_for(ws.recv(), 10))
            while reply["type"] != "pong":
                reply = msgpack.unpackb(await asyncio.wait_for(ws.recv(), 10))
            assert reply["seq"] == 7
            assert peer.frames_in - frames_before == 11
            # The newest of the ten wins: the watcher sees x = 1.0.
            await settle(
                lambda: any(_xs(snap, user) == [pytest.approx(1.0)] for snap in _snaps(watcher))
            )
        await ws.close()
        await watcher.conn.close()


def _snaps(bot: Bot) -> list[Snapshot]:
    return [snap for _, snap in bot.snapshots]


def _xs(snap: Snapshot, user: int) -> list[float]:
    entries = snap.entries
    return [float(pose[0]) for pose in entries["pose"][entries["user"] == user]]


async def test_a_burst_of_events_in_one_read_does_not_overflow_a_reading_peer() -> None:
    """Forty events in one write reach a peer whose queue holds eight: each is written
    to it before the next is handled, so a peer that reads is never too slow."""
    async with running_server(config(max_event_queue=8)) as srv:
        url = f"ws://127.0.0.1:{srv.port}"
        peer = await Bot.join(url, srv.clock, room="e", rate=10.0, streams=("head",))
        ws = await raw_connect(url)
        await raw_join(ws, "e", ("head",))
        events = [encode_message(UserEvent(kind="button", payload={"k": k})) for k in range(40)]
        async with peer.running(publish=False):
            ws.transport.write(b"".join(masked(e) for e in events))
            await settle(lambda: len(peer.of_type(UserEvent)) == 40)
            assert [e.payload["k"] for e in peer.of_type(UserEvent)] == list(range(40))
            assert peer.closed is None
        await ws.close()
        await peer.conn.close()


async def test_writes_wait_while_the_buffer_is_full_then_go_out_in_order() -> None:
    """A subscriber that stops reading pauses our writes: its events wait in the outbox
    (nothing more reaches the transport), and all arrive in order once it reads again."""
    # (no keepalive: a ping written meanwhile would change the buffer this test watches)
    async with running_server(config(max_event_queue=64, ping_interval=0)) as srv:
        url = f"ws://127.0.0.1:{srv.port}"
        streams = ("head", "left", "right", *(f"object:o{i}" for i in range(13)))
        pub = await Bot.join(url, srv.clock, room="p", rate=30.0, streams=streams)
        async with pub.running():
            ws, user = await never_reader(srv, "p")
            conn = srv.connection_of(user)
            await settle(lambda: conn.paused)
            buffered = conn.transport.get_write_buffer_size()
            for k in range(20):
                await pub.conn.send(UserEvent(kind="button", payload={"k": k}))
            await settle(lambda: len(conn.outbox.events) == 20)
            assert conn.transport.get_write_buffer_size() == buffered
            got: list[int] = []
            async with asyncio.timeout(20):
                while len(got) < 20:
                    msg = msgpack.unpackb(await ws.recv())
                    if msg["type"] == "event":
                        got.append(msg["payload"]["k"])
            assert got == list(range(20))
            assert not conn.paused
        await ws.close()
        await pub.conn.close()


async def test_a_connection_that_never_handshakes_is_dropped(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A TCP connection that sends no HTTP request is dropped after the open timeout."""
    monkeypatch.setattr(server_connection, "OPEN_TIMEOUT", 0.3)
    async with running_server(config()) as srv:
        reader, writer = await asyncio.open_connection("127.0.0.1", srv.port)
        async with asyncio.timeout(10):
            assert await reader.read() == b""  # closed by the server
        writer.close()
        await settle(lambda: not srv._sockets)


def test_tick_lag_histogram_counts_each_member_from_its_due_time() -> None:
    """Each due member's lag falls in its bucket; limit=1 ticks one room per call."""
    core = RelayCore()
    connect(core, 1.0, room="a", rate=10.0)
    connect(core, 1.0, room="a", rate=10.0)
    connect(core, 1.0, room="b", rate=10.0)
    due_a = core.rooms["a"].next_due()
    due_b = core.rooms["b"].next_due()
    assert due_a is not None and due_b is not None and due_a != due_b
    late = max(due_a, due_b) + 0.003
    core.tick(late, limit=1)
    assert sum(core.tick_lag_counts) in (1, 2)  # one room: its one or two members
    core.tick(late, limit=1)
    assert sum(core.tick_lag_counts) == 3
    text = metrics_text(core)
    # The later room lags 3 ms (the 5 ms bucket), the earlier one more.
    five = TICK_LAG_BUCKETS.index(0.005)
    assert core.tick_lag_counts[five] >= 1
    assert sum(core.tick_lag_counts[:five]) == 0
    assert 'posecast_tick_lag_seconds_bucket{le="+Inf"} 3' in text
    assert "posecast_tick_lag_seconds_count 3" in text
    buckets = [
        int(line.rsplit(" ", 1)[1])
        for line in text.splitlines()
        if line.startswith("posecast_tick_lag_seconds_bucket")
    ]
    assert buckets == sorted(buckets) and len(buckets) == len(TICK_LAG_BUCKETS) + 1


async def test_metrics_histogram_counts_live_ticks() -> None:
    """Over real sockets, /metrics exports the tick lag histogram with every member tick."""
    async with running_server(config()) as srv:
        url = f"ws://127.0.0.1:{srv.port}"
        bots = [await Bot.join(url, srv.clock, room="m", rate=20.0, seed=i) for i in range(2)]
        async with bots[0].running(), bots[1].running():
            await settle(lambda: all(len(b.snapshots) >= 5 for b in bots))
            _, _, body = await http_get(srv.port, "/metrics")
        m = parse_metrics(body)
        count = m["posecast_tick_lag_seconds_count"][""]
        assert count >= 10
        assert m["posecast_tick_lag_seconds_bucket"]['{le="+Inf"}'] == count
        for bot in bots:
            await bot.conn.close()


def test_the_relay_runs_on_uvloop() -> None:
    """What `posecast serve` runs: uvloop's transports, health, a relayed pose, a clean stop."""

    async def scenario() -> tuple[int, int, float]:
        async with running_server(config()) as srv:
            url = f"ws://127.0.0.1:{srv.port}"
            status, _, _ = await http_get(srv.port, "/healthz")
            a = await ClientConnection.open(url, room="u", streams=("head",), rate=20.0)
            b = await ClientConnection.open(url, room="u", streams=("head",), rate=20.0)
            ids = list(a.joined.streams.values())  # type: ignore[union-attr]
            await a.send(PoseUpdate.from_arrays(1, ids, [a.clock()], POSE))
            async with asyncio.timeout(10):
                while True:
                    rec = await b.recv()
                    if isinstance(rec.event, Snapshot) and len(rec.event.entries):
                        break
            await a.ws.close()
            await b.ws.close()
            return status, len(rec.event.entries), float(rec.event.entries["pose"][0][1])

    status, entries, y = uvloop.run(scenario())
    assert (status, entries) == (200, 1)
    assert y == pytest.approx(1.5)


async def test_stop_drops_a_socket_still_in_its_handshake() -> None:
    """stop() does not wait for a TCP connection that never sent its HTTP request."""
    srv = server_app.RelayServer(config())
    task = asyncio.create_task(srv.run())
    await asyncio.wait_for(srv.ready.wait(), 10)
    sock = socket.create_connection(("127.0.0.1", srv.port or 0))
    await settle(lambda: len(srv._sockets) == 1)
    srv.stop()
    async with asyncio.timeout(5):  # well under the 10 s open timeout
        await task
    sock.close()


async def test_a_bug_handling_one_read_closes_that_connection_1011() -> None:
    """An exception while handling a read ends that connection with 1011; others go on."""
    async with running_server(config()) as srv:
        frame = srv.core.frame
        marker = msgpack.packb({"type": "ping", "seq": 666, "time": 1.0})

        def buggy(conn: int, data: bytes | str) -> list[Any]:
            if data == marker:
                raise RuntimeError("a bug")
            return frame(conn, data)

        srv.core.frame = buggy  # type: ignore[method-assign]
        url = f"ws://127.0.0.1:{srv.port}"
        bot = await Bot.join(url, srv.clock, room="b", rate=20.0, seed=1)
        other = await Bot.join(url, srv.clock, room="b", rate=20.0, seed=2)
        ws = await raw_connect(url)
        await raw_join(ws, "b", ("head",))
        async with bot.running(), other.running():
            await ws.send(marker)
            _, code = await until_closed(ws)
            assert code == 1011
            n = len(bot.snapshots)
            await settle(lambda: len(bot.snapshots) >= n + 5)
            assert bot.closed is None and other.closed is None
        await bot.conn.close()
        await other.conn.close()
