"""A relay's stop: what it says when it waits too long (``server/stopping.py``), and
that a connection the intake took as the relay stopped ends with the stop.

Real relays on loopback (port 0), real clients; the bounds given are what is
waited for, never a timing that is checked.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket

import pytest
from relaykit import raw_connect
from support import poll_until

from posecast.server.app import RelayServer, ServerConfig, serving
from posecast.server.stopping import until_gone, watch_tasks


def _warnings(caplog: pytest.LogCaptureFixture, text: str) -> list[str]:
    return [r.getMessage() for r in caplog.records if text in r.getMessage()]


async def test_connections_left_past_the_bound_are_named(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """One warning names each connection still open: its peer, its websocket state."""
    server = RelayServer(ServerConfig(host="127.0.0.1", port=0, handshake_timeout=60.0))
    async with serving(server):
        ws = await raw_connect(f"ws://127.0.0.1:{server.port}")
        _, writer = await asyncio.open_connection("127.0.0.1", server.port)  # no handshake
        await poll_until(lambda: len(server._sockets) == 2)
        with caplog.at_level(logging.WARNING, "posecast.server"):
            # Nothing closes them: the bound passes with both still open.
            assert not await until_gone(server._sockets, server._all_gone, 0.2)
        (said,) = _warnings(caplog, "did not end")
        assert said.startswith("stopping: 2 connections did not end within 0.2 s; aborted: ")
        ws_port = ws.local_address[1]
        tcp_port = writer.get_extra_info("sockname")[1]
        assert f"127.0.0.1:{ws_port} OPEN open" in said
        assert f"127.0.0.1:{tcp_port} CONNECTING no websocket yet" in said
        await ws.close()
        writer.close()
    assert server._all_gone.is_set()


async def test_tasks_a_stop_waits_for_are_named(caplog: pytest.LogCaptureFixture) -> None:
    """A task that lost its cancellation (as a NATS reply through asyncio.wait_for can
    make one on Python 3.11) is named, said cancelled, with where it waits."""
    release = asyncio.Event()

    async def deaf() -> None:
        # (lost, as wait_for loses it when the reply comes with it)
        with contextlib.suppress(asyncio.CancelledError):
            await asyncio.Event().wait()
        await release.wait()

    task = asyncio.create_task(deaf(), name="deaf-upkeep")
    await asyncio.sleep(0)
    task.cancel()
    with caplog.at_level(logging.WARNING, "posecast.server"):
        watch_tasks(0.01)
        await poll_until(lambda: bool(_warnings(caplog, "still waiting")))
    (said,) = _warnings(caplog, "still waiting")
    assert "deaf-upkeep cancelled 1x at " in said
    assert "test_stopping.py:" in said and " deaf" in said
    release.set()
    await task
    # A stop that ended first says nothing.
    caplog.clear()
    with caplog.at_level(logging.WARNING, "posecast.server"):
        watch_tasks(0.01).cancel()
        await asyncio.sleep(0.05)
    assert _warnings(caplog, "still waiting") == []


async def test_a_connection_the_intake_took_as_the_relay_stopped_ends_with_the_stop(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The intake accepts a queued connection; the relay stops before the socket is
    handed over to the loop. It is closed with the stop, not left open after it
    (it would be until its handshake timeout, 60 s here) nor waited for."""
    server = RelayServer(ServerConfig(host="127.0.0.1", port=0, handshake_timeout=60.0))
    loop = asyncio.get_running_loop()
    client = socket.socket()
    client.setblocking(False)
    with caplog.at_level(logging.WARNING, "posecast.server"):
        async with serving(server):
            assert server._intake is not None
            # Loopback: the connection is queued when connect_ex returns; the intake
            # takes it before the loop's own accept can (no await in between).
            client.connect_ex(("127.0.0.1", server.port))
            assert server._intake.accept() == 1
            server.stop()
        try:
            async with asyncio.timeout(30):  # (a hang guard)
                got = await loop.sock_recv(client, 1)
        except ConnectionResetError:  # (closed by an abort)
            got = b""
    client.close()
    assert got == b""  # the relay closed it
    assert server._sockets == set()
    assert _warnings(caplog, "stopping") == []
    assert _warnings(caplog, "accepting a connection failed") == []
