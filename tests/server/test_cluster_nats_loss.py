"""NATS lost while a cluster node serves: its rooms go on; when NATS is back (a new
nats-server on the same port, its memory gone) the node takes its leases again."""

from __future__ import annotations

import logging
import socket
from pathlib import Path

import pytest
from conftest import needs_nats
from relaykit import Bot, settle
from support import running_server

from posecast.server.app import ServerConfig
from posecast.server.cluster import Directory, LocalNats

pytestmark = needs_nats


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def test_a_node_keeps_its_rooms_without_nats_and_rejoins_after(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    port = free_port()
    nats_1 = await LocalNats.start(tmp_path / "n1", port=port)
    url = f"nats://127.0.0.1:{port}"
    cfg = ServerConfig(host="127.0.0.1", port=0, cluster=url, node="a", cluster_lease=1.5)
    caplog.set_level(logging.WARNING, logger="posecast.cluster")
    try:
        async with running_server(cfg) as srv:
            assert srv.cluster is not None
            ws = f"ws://127.0.0.1:{srv.port}"
            pub = await Bot.join(ws, srv.clock, room="lab", rate=20.0, seed=1)
            sub = await Bot.join(ws, srv.clock, room="lab", rate=20.0, seed=2)
            async with pub.running(), sub.running(publish=False):
                await settle(lambda: len(sub.snapshots) > 5)
                nats_1.kill()
                await nats_1.stop()
                await settle(lambda: srv.cluster is not None and srv.cluster.directory.unreachable)
                # The room goes on: snapshots keep coming while NATS is away.
                before = len(sub.snapshots)
                await settle(lambda: len(sub.snapshots) > before + 10)
                assert "NATS unreachable" in caplog.text
                metrics = srv.metrics_text()
                assert "posecast_cluster_nats_up 0" in metrics
                nats_2 = await LocalNats.start(tmp_path / "n2", port=port)
                try:
                    await settle(lambda: not srv.cluster.directory.unreachable, limit=20.0)  # type: ignore[union-attr]
                    assert "NATS is back" in caplog.text
                    # Its leases are in the new NATS: the node, and the room it owns.
                    probe = await Directory.open(url, "probe", lease=1.5)
                    try:
                        assert await probe.owner("lab") == "a"
                        assert "a" in await probe.nodes()
                    finally:
                        await probe.close()
                    assert len(sub.snapshots) > before + 10
                finally:
                    await pub.conn.close()
                    await sub.conn.close()
                    await nats_2.stop()
    finally:
        await nats_1.stop()
