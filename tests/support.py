"""Test support shared by every test package: a real relay on loopback."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from server.app import RelayServer, ServerConfig

__all__ = ["running_server"]


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
