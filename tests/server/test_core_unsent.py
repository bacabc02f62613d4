"""A socket's unsent bytes reach the core as a number (``RelayCore.buffered``), told by
the adapter after each write and again before each tick while some remain: a room's
tick skips a congested subscriber, and gives it snapshots again once it reads.
"""

from __future__ import annotations

import asyncio
import contextlib

from relaykit import Bot, never_reader, settle
from support import running_server
from websockets.exceptions import ConnectionClosed

from posecast.server.app import ServerConfig
from posecast.server.core import RelayCore


def test_the_core_holds_the_number_it_is_told() -> None:
    """``buffered(conn, n)`` sets the outbox's number; an ended connection is ignored."""
    core = RelayCore(ServerConfig(congested_bytes=100))
    conn = core.connect(1.0)
    outbox = core.peer(conn).outbox
    assert outbox.buffered == 0 and not outbox.congested()
    core.buffered(conn, 101)
    assert outbox.buffered == 101 and outbox.congested()
    core.buffered(conn, 0)
    assert not outbox.congested()
    core.disconnect(conn, 2.0)
    core.buffered(conn, 5)  # (gone: nothing to tell)


async def test_a_stuck_subscriber_is_skipped_then_served_once_it_reads() -> None:
    """A subscriber that stops reading fills its socket: the core, told the number, skips
    its snapshots (congestion skips); once it reads, the loop sends what waited, the
    core is told before the next tick, and its snapshots flow again."""
    cfg = ServerConfig(host="127.0.0.1", port=0, congested_bytes=2048, ping_interval=0)
    streams = ("head", "left", "right", *(f"object:o{i}" for i in range(13)))
    async with running_server(cfg) as srv:
        url = f"ws://127.0.0.1:{srv.port}"
        pub = await Bot.join(url, srv.clock, room="p", rate=30.0, streams=streams)
        async with pub.running():
            ws, user = await never_reader(srv, "p")
            await settle(lambda: user in srv.rooms["p"].members)
            member = srv.rooms["p"].members[user]
            outbox = srv.connection_of(user).outbox
            await settle(lambda: member.congestion_skips >= 3)
            assert outbox.buffered > cfg.congested_bytes  # the number the core was told
            sent = member.snapshots

            async def read() -> None:
                with contextlib.suppress(ConnectionClosed):
                    async for _ in ws:
                        pass

            reader = asyncio.create_task(read())
            await settle(lambda: member.snapshots >= sent + 10)
            reader.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await reader
        await ws.close()
        await pub.conn.close()
