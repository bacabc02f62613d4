"""Test support shared by every test package: a real relay on loopback."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager

from server.app import RelayServer, ServerConfig

__all__ = ["poll_until", "relayed", "running_server"]


@asynccontextmanager
async def running_server(config: ServerConfig | None = None) -> AsyncIterator[RelayServer]:
    """Run a RelayServer on 127.0.0.1:0 inside a TaskGroup; stop it on exit."""
    cfg = config or ServerConfig(host="127.0.0.1", port=0)
    server = RelayServer(cfg)
    async with asyncio.TaskGroup() as tg:
        tg.create_task(server.run())
        await asyncio.wait_for(server.ready.wait(), 10)
        try:
            yield server
        finally:
            server.stop()


async def poll_until(condition: Callable[[], bool], limit: float = 60.0) -> None:
    """Poll ``condition``; ``limit`` is a hang guard, not a timing check."""
    async with asyncio.timeout(limit):
        while True:
            if condition():
                return
            await asyncio.sleep(0.02)


def relayed(server: RelayServer, room: str) -> int:
    """Poses the relay has sent out in ``room`` so far (0 before the room exists)."""
    r = server.rooms.get(room)
    return 0 if r is None else r.statistics().poses_out
