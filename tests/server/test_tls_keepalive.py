"""wss:// with a certificate made in the test (trustme), and dead peers found by keepalive.

A real relay on loopback serves TLS; clients trust it through a CA file, refuse it
without one, or skip the check with ``insecure``; a bot runs over wss:// end to
end. A peer that stops answering pings is closed by the server, alone.
"""

from __future__ import annotations

import asyncio
import ssl
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import trustme
import uvloop
from relaykit import settle
from support import running_server
from typer.testing import CliRunner

from posecast.cli import app
from posecast.client.bot import BotConfig, run_bot
from posecast.client.connection import ClientConnection, Tls
from posecast.protocol import PoseUpdate, Snapshot
from posecast.server.app import ServerConfig

POSE = np.array([[0.0, 1.6, 0.0, 1.0, 0.0, 0.0, 0.0]] * 3)


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Path, Path, Path]]:
    """(CA file, server certificate chain, server key) for 127.0.0.1, as PEM files."""
    folder = tmp_path_factory.mktemp("pki")
    ca = trustme.CA()
    cert = ca.issue_cert("127.0.0.1", "localhost")
    ca_file, chain, key = folder / "ca.pem", folder / "chain.pem", folder / "key.pem"
    ca.cert_pem.write_to_path(ca_file)
    cert.private_key_pem.write_to_path(key)
    chain.write_bytes(b"".join(blob.bytes() for blob in cert.cert_chain_pems))
    yield ca_file, chain, key


def _config(pki: tuple[Path, Path, Path]) -> ServerConfig:
    return ServerConfig(host="127.0.0.1", port=0, certfile=pki[1], keyfile=pki[2])


async def _relay_once(url: str, tls: Tls) -> Snapshot:
    a = await ClientConnection.open(
        url, room="tls", streams=("head", "left", "right"), rate=20, tls=tls
    )
    b = await ClientConnection.open(
        url, room="tls", streams=("head", "left", "right"), rate=20, tls=tls
    )
    try:
        ids = list(a.joined.streams.values())  # type: ignore[union-attr]
        await a.send(PoseUpdate.from_arrays(1, ids, np.full(3, a.clock()), POSE))
        async with asyncio.timeout(10):
            while True:
                rec = await b.recv()
                if isinstance(rec.event, Snapshot) and len(rec.event.entries):
                    return rec.event
    finally:
        await a.ws.close()
        await b.ws.close()


async def test_wss_with_the_ca_file_relays_poses(pki: tuple[Path, Path, Path]) -> None:
    async with running_server(_config(pki)) as srv:
        snap = await _relay_once(f"wss://127.0.0.1:{srv.port}", Tls(cafile=str(pki[0])))
    assert len(snap.entries) == 3


async def test_wss_without_trust_is_refused_and_insecure_is_not(
    pki: tuple[Path, Path, Path],
) -> None:
    async with running_server(_config(pki)) as srv:
        url = f"wss://127.0.0.1:{srv.port}"
        with pytest.raises(ssl.SSLCertVerificationError):
            await ClientConnection.connect(url)
        snap = await _relay_once(url, Tls(insecure=True))
        # A plain ws:// client gets no websocket from a TLS port.
        with pytest.raises(Exception):  # noqa: B017 - any handshake failure will do
            await ClientConnection.connect(f"ws://127.0.0.1:{srv.port}", open_timeout=3)
    assert len(snap.entries) == 3


async def test_a_bot_runs_over_wss(pki: tuple[Path, Path, Path]) -> None:
    async with running_server(_config(pki)) as srv:
        url = f"wss://127.0.0.1:{srv.port}"
        cfg = dict(url=url, room="b", rate=15, duration=2.0, methods=("soa",), cafile=str(pki[0]))
        async with asyncio.TaskGroup() as tg:
            tasks = [
                tg.create_task(run_bot(BotConfig(**cfg, name=f"b{i}", seed=i))) for i in range(2)
            ]  # type: ignore[arg-type]
    for t in tasks:
        rep = t.result()
        assert rep.ending.kind == "complete" and rep.poses_received > 0


def test_serve_refuses_half_or_bad_tls_files_in_one_line(pki: tuple[Path, Path, Path]) -> None:
    runner = CliRunner()
    res = runner.invoke(app, ["serve", "--certfile", str(pki[1])])
    assert res.exit_code == 2 and "both --certfile and --keyfile" in res.output
    res = runner.invoke(app, ["serve", "--certfile", str(pki[0]), "--keyfile", str(pki[0])])
    assert res.exit_code == 2 and "not a usable PEM" in res.output


async def test_a_peer_that_stops_answering_pings_is_closed_alone() -> None:
    cfg = ServerConfig(host="127.0.0.1", port=0, ping_interval=0.2, ping_timeout=0.2)
    async with running_server(cfg) as srv:
        url = f"ws://127.0.0.1:{srv.port}"
        streams = ("head", "left", "right")
        alive = await ClientConnection.open(url, room="k", streams=streams, rate=20)
        frozen = await ClientConnection.open(url, room="k", streams=streams, rate=20)
        # The frozen client's process stops reading its socket: no pong ever comes back.
        frozen.ws.transport.pause_reading()
        await settle(lambda: srv.core.closed_connections >= 1, limit=20)
        # The live one answered every ping and is still in the room.
        room = srv.core.rooms["k"]
        assert alive.session.user in room.members and frozen.session.user not in room.members
        await alive.ws.close()
        frozen.ws.transport.abort()


def test_wss_on_uvloop_relays_poses(pki: tuple[Path, Path, Path]) -> None:
    """`posecast serve` runs on uvloop: its TLS transports carry the relay too."""

    async def scenario() -> Snapshot:
        async with running_server(_config(pki)) as srv:
            return await _relay_once(f"wss://127.0.0.1:{srv.port}", Tls(cafile=str(pki[0])))

    assert len(uvloop.run(scenario()).entries) == 3
