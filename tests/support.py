"""Test support shared by every test package: a real relay on loopback."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from contextlib import AbstractAsyncContextManager

from server.app import RelayServer, ServerConfig, serving

__all__ = ["poll_until", "relayed", "running_server"]


def running_server(config: ServerConfig | None = None) -> AbstractAsyncContextManager[RelayServer]:
    """Run a RelayServer on 127.0.0.1:0 while the block runs; stop it on exit."""
    return serving(RelayServer(config or ServerConfig(host="127.0.0.1", port=0)))


async def poll_until(
    condition: Callable[[], bool], limit: float = 60.0, every: float = 0.02
) -> None:
    """Poll ``condition`` every ``every`` s until it holds; ``limit`` is a hang guard
    (TimeoutError), not a timing check."""
    async with asyncio.timeout(limit):
        while True:
            if condition():
                return
            await asyncio.sleep(every)


def relayed(server: RelayServer, room: str) -> int:
    """Poses the relay has sent out in ``room`` so far (0 before the room exists)."""
    r = server.rooms.get(room)
    return 0 if r is None else r.statistics().poses_out
