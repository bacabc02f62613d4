"""Connections before their handshake count against the caps; /healthz always answers.

The counting rules on :class:`server.handshakes.Handshakes` alone, then over real
loopback sockets: silent TCP connections (a slowloris) hold the per-address cap,
a websocket over it is closed 1013 after its handshake while ``/healthz`` and ``/metrics`` are
still answered on the spare places, connections over those are dropped unread,
and the silent ones are dropped at the handshake deadline.
"""

from __future__ import annotations

import asyncio

import pytest
from support import poll_until, running_server
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

from posecast.server.core import ServerConfig
from posecast.server.handshakes import Handshakes
from posecast.server.limits import Admission


def test_pending_and_open_connections_share_the_caps() -> None:
    """Pending handshakes and open connections count together, per address too; over a
    cap a connection gets a spare place, then nothing."""
    admission = Admission(max_total=4, max_per_address=2)
    shakes = Handshakes(admission, reserve=1)
    assert shakes.admit("a", 0.0) == "handshake"
    admission.admit("a")  # one open connection of a
    assert shakes.admit("a", 0.0) == "probe"  # a: 1 pending + 1 open
    assert shakes.admit("a", 0.0) is None and shakes.refused == 1
    assert shakes.admit("b", 0.0) == "handshake"
    assert shakes.admit("c", 0.0) == "handshake"  # 3 pending + 1 open: full
    assert shakes.admit("d", 0.0) is None
    shakes.release("handshake", "c")
    shakes.release("probe", "a")
    assert shakes.admit("d", 0.0) == "handshake" and shakes.pending == 3
    assert shakes.by_address == {"a": 1, "b": 1, "d": 1}


def test_at_the_total_cap_the_oldest_slow_handshake_gives_way() -> None:
    """At the total cap a new connection takes the place of the oldest handshake pending
    for ``evict_after`` s or more (named by take_evicted, released once); a younger one
    keeps its place, and the per-address cap is not bypassed."""
    admission = Admission(max_total=2, max_per_address=2)
    shakes = Handshakes(admission, reserve=0)
    assert shakes.admit("a", 0.0, key="k1") == "handshake"
    assert shakes.admit("b", 0.2, key="k2") == "handshake"
    assert shakes.admit("c", 0.4, key="k3") is None  # k1 waited 0.4 s: it keeps its place
    assert shakes.take_evicted() == [] and shakes.evicted == 0
    assert shakes.admit("c", 0.5, key="k4") == "handshake"
    assert shakes.take_evicted() == ["k1"] and shakes.evicted == 1
    assert shakes.pending == 2 and shakes.by_address == {"b": 1, "c": 1}
    shakes.release("handshake", "a", key="k1")  # the dropped one ends: counted once
    assert shakes.pending == 2 and shakes.by_address == {"b": 1, "c": 1}
    shakes.release("handshake", "b", key="k2")  # a handshake done
    assert shakes.pending == 1 and shakes.by_address == {"c": 1}
    assert shakes.admit("c", 0.9, key="k5") == "handshake"
    assert shakes.admit("c", 9.0, key="k6") is None  # c at its own cap of 2: no eviction
    assert shakes.take_evicted() == []


async def _http(port: int, path: str) -> bytes:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(f"GET {path} HTTP/1.1\r\nHost: relay\r\n\r\n".encode())
    async with asyncio.timeout(5):
        data = await reader.read()
    writer.close()
    return data


async def _silent(port: int) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(b"GET / HTTP/1.1\r\n")  # a request that never ends
    await writer.drain()
    return reader, writer


async def _dropped(reader: asyncio.StreamReader) -> bool:
    """The relay closed this connection (hang guard only, no timing check)."""
    async with asyncio.timeout(10):
        return await reader.read() == b""


def _metric(text: bytes, name: str) -> float:
    for line in text.decode().splitlines():
        if line.startswith(name + " ") or line.startswith(name + "{"):
            return float(line.rsplit(" ", 1)[1])
    raise KeyError(name)


async def test_a_slowloris_holds_no_more_than_its_cap_and_healthz_answers() -> None:
    """Silent upgrades fill the per-address cap; a websocket over it gets 1013, /healthz
    and /metrics still answer, and beyond the spare places a socket is dropped unread."""
    cfg = ServerConfig(host="127.0.0.1", port=0, max_connections_per_address=3,
                       handshake_timeout=60.0)  # fmt: skip
    async with running_server(cfg) as srv:
        assert srv.port is not None
        slow = [await _silent(srv.port) for _ in range(3)]
        await poll_until(lambda: srv.core.handshakes.pending == 3)
        async with connect(f"ws://127.0.0.1:{srv.port}") as ws:
            with pytest.raises(ConnectionClosed):
                await ws.recv()
        assert ws.close_code == 1013 and srv.core.refused_connections == 1
        assert (await _http(srv.port, "/healthz")).startswith(b"HTTP/1.1 200")
        metrics = await _http(srv.port, "/metrics")
        assert metrics.startswith(b"HTTP/1.1 200")
        assert 'posecast_handshakes_pending{place="handshake"} 3' in metrics.decode()
        shakes = srv.core.handshakes
        await poll_until(lambda: shakes.probes == 0)  # the probes above have ended
        shakes.reserve = 1
        spare = await _silent(srv.port)  # takes the one spare place
        await poll_until(lambda: shakes.probes == 1)
        over = await _silent(srv.port)
        assert await _dropped(over[0])
        assert srv.core.handshakes.refused == 1
        for _, writer in (*slow, spare, over):
            writer.close()


async def test_silent_connections_are_dropped_at_the_handshake_deadline() -> None:
    """A connection that never finishes its request is dropped, counted as a timeout,
    and its place is free again: a websocket client connects after."""
    cfg = ServerConfig(host="127.0.0.1", port=0, max_connections_per_address=2,
                       handshake_timeout=0.2)  # fmt: skip
    async with running_server(cfg) as srv:
        assert srv.port is not None
        slow = [await _silent(srv.port) for _ in range(2)]
        for reader, writer in slow:
            assert await _dropped(reader)
            writer.close()
        assert srv.core.handshakes.timeouts == 2 and srv.core.handshakes.pending == 0
        async with connect(f"ws://127.0.0.1:{srv.port}") as ws:
            await ws.ping()
        text = srv.metrics_text()
        assert _metric(text.encode(), 'posecast_handshakes_refused_total{reason="timeout"}') == 2


async def test_slow_upgrades_at_the_total_cap_do_not_lock_a_user_out() -> None:
    """Silent upgrades from one address each (as from many machines) fill the relay's
    total cap; a websocket client still gets in, in the place of the oldest."""
    cfg = ServerConfig(host="127.0.0.1", port=0, max_connections=3, handshake_timeout=60.0)
    async with running_server(cfg) as srv:
        assert srv.port is not None
        shakes = srv.core.handshakes
        shakes.evict_after = 0.0  # (0.5 s by default: no waiting in a test)
        slow = [await _silent(srv.port) for _ in range(3)]
        await poll_until(lambda: shakes.pending == 3)
        async with connect(f"ws://127.0.0.1:{srv.port}") as ws:
            await (await ws.ping())  # a pong: open, not closed 1013 over the cap
        assert await _dropped(slow[0][0])
        assert shakes.evicted >= 1 and srv.core.refused_connections == 0
        text = srv.metrics_text()
        assert _metric(text.encode(), 'posecast_handshakes_refused_total{reason="evicted"}') >= 1
        for _, writer in slow:
            writer.close()
