"""A real relay server on loopback (port 0) for the server and client tests."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager

import pytest

from server.app import RelayServer, ServerConfig


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


@pytest.fixture
def server_factory() -> Callable[..., object]:
    return running_server
