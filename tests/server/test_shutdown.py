"""Shutdown: stop() closes every connection with 1001 "going away" and run() returns;
``posecast serve`` does the same on SIGTERM and SIGINT and exits 0.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import signal
import subprocess
import sys
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

import msgpack
import pytest
from relaykit import HELLO, Bot, join_frame, never_reader, raw_connect, settle
from websockets.asyncio.client import ClientConnection as WsConnection
from websockets.exceptions import ConnectionClosed

from posecast.client.connection import ClientConnection
from posecast.server.app import RelayServer, ServerConfig

CLI = [sys.executable, "-c", "from posecast.cli import main; main()"]
LISTENING = re.compile(r"posecast listening on ws://(?P<host>[^\s:]+):(?P<port>\d+)")


@asynccontextmanager
async def started(config: ServerConfig) -> AsyncIterator[tuple[RelayServer, asyncio.Task[None]]]:
    """A RelayServer whose run() task the test watches; cancelled only if it hangs."""
    srv = RelayServer(config)
    task = asyncio.create_task(srv.run())
    try:
        async with asyncio.timeout(10):
            await srv.ready.wait()
        yield srv, task
    finally:
        if not task.done():
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)


async def close_of(ws: WsConnection) -> tuple[int | None, str | None]:
    """Read until the connection ends; the server's close code and reason."""
    try:
        async with asyncio.timeout(10):
            while True:
                await ws.recv()
    except ConnectionClosed as exc:
        rcvd = exc.rcvd
        return (rcvd.code, rcvd.reason) if rcvd is not None else (None, None)


async def bot_close(bot: Bot) -> tuple[int | None, str | None]:
    """The close code and reason a running bot's recorder saw."""
    await settle(lambda: bot.closed is not None)
    assert bot.closed is not None
    rcvd = bot.closed.rcvd
    return (rcvd.code, rcvd.reason) if rcvd is not None else (None, None)


def config(**kw: Any) -> ServerConfig:
    return ServerConfig(host="127.0.0.1", port=0, **kw)


async def test_stop_closes_everyone_1001_and_run_returns() -> None:
    """Joined, merely greeted and silent connections all get 1001 "going away"; run() ends."""
    async with started(config()) as (srv, task):
        url = f"ws://127.0.0.1:{srv.port}"
        bots = [
            await Bot.join(url, srv.clock, room=room, rate=10.0, seed=i)
            for i, room in enumerate(("a", "a", "b"))
        ]
        greeted = await raw_connect(url)
        await greeted.send(HELLO)
        assert msgpack.unpackb(await greeted.recv())["type"] == "welcome"
        silent = await raw_connect(url)
        async with bots[0].running(), bots[1].running(publish=False), bots[2].running():
            await settle(lambda: len(bots[1].snapshots) >= 2)
            srv.stop()
            closes = await asyncio.gather(*(bot_close(b) for b in bots), close_of(greeted))
            closes.append(await close_of(silent))
        assert closes == [(1001, "going away")] * 5
        async with asyncio.timeout(10):
            await task
        assert task.exception() is None
        assert srv.rooms == {}
        assert srv.statistics()["connections"] == 0


async def test_stop_idle_server_returns() -> None:
    """A server with no connections stops at once and frees its port."""
    async with started(config()) as (srv, task):
        srv.stop()
        async with asyncio.timeout(10):
            await task
        with pytest.raises(OSError):
            await raw_connect(f"ws://127.0.0.1:{srv.port}")


async def test_stop_completes_despite_a_client_that_never_reads() -> None:
    """A peer that stopped reading cannot hold shutdown: it is dropped after close_timeout."""
    async with started(config(close_timeout=0.5)) as (srv, task):
        url = f"ws://127.0.0.1:{srv.port}"
        streams = ("head", "left", "right", *(f"object:o{i}" for i in range(13)))
        pub = await Bot.join(url, srv.clock, room="r", rate=20.0, streams=streams)
        pub2 = await Bot.join(url, srv.clock, room="r", rate=20.0, streams=streams, seed=2)
        async with pub.running(), pub2.running():
            stuck, user = await never_reader(srv, "r")
            conn = srv.connection_of(user)
            await settle(lambda: conn.outbox.skips > 0)  # its writer is blocked for good
            srv.stop()
            assert await bot_close(pub) == (1001, "going away")
        async with asyncio.timeout(10):
            await task
        assert srv.statistics()["connections"] == 0
        stuck.transport.abort()


async def test_stop_is_idempotent() -> None:
    """Calling stop() twice is harmless; clients still see one 1001 close."""
    async with started(config()) as (srv, task):
        conn = await ClientConnection.open(
            f"ws://127.0.0.1:{srv.port}", room="r", streams=("head",), rate=10.0
        )
        srv.stop()
        srv.stop()
        assert await close_of(conn.ws) == (1001, "going away")
        async with asyncio.timeout(10):
            await task


class _Stopped:
    """Stands in for the server's stop event once stop() has begun (run() awaits the real one)."""

    def is_set(self) -> bool:
        return True


async def test_a_handshake_finishing_after_stop_is_closed_in_the_core() -> None:
    """A connection accepted after stop() gets 1001, and the core knows it is closing:
    nothing it sends is handled (no hello, no join) and nothing is queued to it."""
    async with started(config()) as (srv, _task):
        peers: list[Any] = []
        handled: list[object] = []
        connect, handle = srv.core.connect, srv.core.handle

        def connect_spy(now: float, address: Any = None) -> int:
            conn = connect(now, address)
            peers.append(srv.core.peer(conn))
            return conn

        def handle_spy(conn: int, event: object, now: float, wall: float = 0.0) -> list[Any]:
            handled.append(event)
            return handle(conn, event, now, wall)  # type: ignore[arg-type]

        srv.core.connect = connect_spy  # type: ignore[method-assign]
        srv.core.handle = handle_spy  # type: ignore[method-assign]
        srv._stop = _Stopped()  # type: ignore[assignment]
        ws = await raw_connect(f"ws://127.0.0.1:{srv.port}")
        with contextlib.suppress(ConnectionClosed):
            await ws.send(HELLO)
            await ws.send(join_frame("r"))
        assert await close_of(ws) == (1001, "going away")
        await settle(lambda: srv.core.closed_connections == 1)
        assert [p.close_request for p in peers] == [(1001, "going away")]
        assert handled == [] and srv.rooms == {}


# -- the command line -------------------------------------------------------------------


def serve_available() -> bool:
    out = subprocess.run([*CLI, "--help"], capture_output=True, text=True, timeout=60)
    return re.search(r"\bserve\b", out.stdout) is not None


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
async def test_cli_serve_signal_closes_1001_exits_0(sig: signal.Signals) -> None:
    """`posecast serve --port 0` prints its URL; on the signal clients get 1001 and it exits 0."""
    if not await asyncio.to_thread(serve_available):
        pytest.skip("`posecast serve` is not in `posecast --help` yet")
    proc = await asyncio.create_subprocess_exec(
        *CLI,
        "serve",
        "--host",
        "127.0.0.1",
        "--port",
        "0",
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    try:
        assert proc.stdout is not None and proc.stderr is not None
        async with asyncio.timeout(30):
            while (match := LISTENING.search((await proc.stdout.readline()).decode())) is None:
                assert proc.returncode is None
        url = f"ws://{match['host']}:{match['port']}"
        conn = await ClientConnection.open(url, room="r", streams=("head",), rate=10.0)
        other = await ClientConnection.open(url, room="r", streams=("head",), rate=10.0)
        proc.send_signal(sig)
        assert await close_of(conn.ws) == (1001, "going away")
        assert await close_of(other.ws) == (1001, "going away")
        async with asyncio.timeout(30):
            _, err = await proc.communicate()
        assert proc.returncode == 0, err.decode()[-2000:]
        assert b"Traceback" not in err, err.decode()[-2000:]
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
