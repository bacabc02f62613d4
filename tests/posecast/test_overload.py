"""A full relay answers every join of a storm: ``server-full``, never silence.

``bench relay --clients 2000 --shed`` on a busy machine left 136 joins hanging:
while the relay's event loop was late, connections past the listen backlog (100,
asyncio's default) were dropped by the kernel, and their clients waited for SYN
retransmissions (1, 3, 7, 15 s) instead of an answer. Here the relay's loop is
held busy (this test blocks it) while a storm of clients connects and sends its
upgrade and ``hello``: the kernel must queue every connection, and once the loop
runs again every client must get ``server-full`` and close 1013. The relay's
intake (``server/intake.py``) takes a batch of the queue at once, where uvloop's
own accept takes one connection a turn of the loop. No wall-clock time is
asserted: the limits are hang guards.
"""

from __future__ import annotations

import asyncio
import base64
import os
import select
import socket
from pathlib import Path

import pytest
from support import poll_until, running_server

from posecast.bench.loadclient import SERVER_FULL, _BenchClient, _LoadStats
from posecast.bench.wsclient import client_frame
from posecast.protocol import ClientSession, Hello
from posecast.server.app import ServerConfig
from posecast.server.intake import BATCH

#: A budget no member fits: once one member is measured, every newcomer is refused
#: (the connection caps lifted, as ``bench relay`` does: the storm comes from one address).
TINY = ServerConfig(
    host="127.0.0.1",
    port=0,
    capacity_cpu=1e-9,
    capacity_min_members=0,
    max_connections=0,
    max_connections_per_address=0,
)
#: Clients in the storm: more than asyncio's default listen backlog (100).
STORM = 300
#: Hang guard (s) for the kernel to complete the storm's TCP handshakes.
CONNECT_GUARD = 10.0


def _somaxconn() -> int:
    try:
        return int(Path("/proc/sys/net/core/somaxconn").read_text())
    except (OSError, ValueError):
        return 4096  # (not Linux: the listen() backlog is taken as asked)


def _connect_all(port: int, n: int) -> list[socket.socket]:
    """``n`` TCP connections to ``port``, made while the caller blocks the event loop:
    those the kernel completes within the hang guard (the relay accepts none meanwhile)."""
    pending: dict[int, socket.socket] = {}
    for _ in range(n):
        s = socket.socket()
        s.setblocking(False)
        s.connect_ex(("127.0.0.1", port))
        pending[s.fileno()] = s
    done: list[socket.socket] = []
    poll = select.poll()
    for fd in pending:
        poll.register(fd, select.POLLOUT)
    deadline = asyncio.get_running_loop().time() + CONNECT_GUARD
    while pending and (left := deadline - asyncio.get_running_loop().time()) > 0:
        for fd, _ in poll.poll(left * 1e3):
            poll.unregister(fd)
            s = pending.pop(fd)
            if s.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR) == 0:
                done.append(s)
            else:
                s.close()
    for s in pending.values():
        s.close()
    return done


def _upgrade_and_hello(port: int) -> bytes:
    """An upgrade request and a ``hello`` frame, as one write."""
    key = base64.b64encode(os.urandom(16))
    request = (
        b"GET / HTTP/1.1\r\nHost: 127.0.0.1:%d\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
        b"Sec-WebSocket-Key: %s\r\nSec-WebSocket-Version: 13\r\n\r\n" % (port, key)
    )
    hello = ClientSession().send(Hello(agent="storm", wants_retry_after=True))
    return request + client_frame(hello)


async def _answer(sock: socket.socket) -> bytes:
    """Everything the relay wrote on ``sock`` until it closed the connection."""
    reader, writer = await asyncio.open_connection(sock=sock)
    try:
        return await reader.read(-1)
    finally:
        writer.close()


async def _storm() -> tuple[int, list[bytes], float, str, int]:
    stats = _LoadStats(1)
    holder = _BenchClient(0, "held", 20.0, stats, "compact")
    async with running_server(TINY) as server:
        assert server.port is not None
        await holder.open(f"ws://127.0.0.1:{server.port}", 30.0)
        cap = server.core.capacity
        await poll_until(lambda: cap.cpu_members > 0 and cap.cpu > 0)
        assert cap.refusal(1, server.clock()) is not None  # full from now on
        # The loop is blocked from here to the awaits below: the relay accepts nothing.
        socks = _connect_all(server.port, STORM)
        connected = len(socks)
        # The tick timer's intake takes a batch of the queue at once (uvloop's own
        # accept takes one connection a turn of the loop).
        assert server._intake is not None
        taken = server._intake.accept()
        for s in socks:
            s.setblocking(True)
            s.sendall(_upgrade_and_hello(server.port))
            s.setblocking(False)
        async with asyncio.timeout(60.0):  # hang guard
            answers = await asyncio.gather(*(_answer(s) for s in socks))
        assert holder.conn is not None
        holder.conn.abort()
        metrics = server.metrics_text()
    return connected, answers, cap.join_cpu, metrics, taken


@pytest.mark.skipif(_somaxconn() < STORM + 10, reason="net.core.somaxconn below the storm")
def test_a_storm_of_joins_on_a_busy_full_relay_is_refused_not_dropped() -> None:
    """Every connection of the storm is queued while the loop is busy, and every one
    gets the ``server-full`` error and close 1013 (none silence, none a reset)."""
    connected, answers, join_cpu, metrics, taken = asyncio.run(_storm())
    assert connected == STORM, f"{STORM - connected} connections dropped by the kernel"
    assert taken == BATCH
    refused = [a for a in answers if a.startswith(b"HTTP/1.1 101") and SERVER_FULL.encode() in a]
    assert len(refused) == STORM, f"{STORM - len(refused)} got no server-full: {answers[:1]}"
    # The close frame (opcode 8) carries 1013 "try again later".
    assert all(b"\x88" in a and (1013).to_bytes(2, "big") in a for a in answers)
    # The storm's work was measured apart from the members' (``Capacity.join_work``).
    assert join_cpu > 0
    samples = dict(line.rpartition(" ")[::2] for line in metrics.splitlines() if line[:1] != "#")
    assert float(samples["posecast_join_cpu_seconds_total"]) > 0
    assert "posecast_ticks_late_for_joins_total" in samples
