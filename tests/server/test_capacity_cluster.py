"""A full cluster node hands its client to another node (#28): two real nodes over a
real nats-server, one of them over its measured budget. A bot given both nodes' URLs
is refused ``server-full`` by the full node at its hello, moves on to the other node,
and that node claims the bot's room and serves it. A room the full node owns stays
its own: a join for it through the other node is forwarded to the full node and
refused there (it would carry the member's fan-out), with ``server-full`` and close
1013 passed back, and the room's members hear nothing of it.
"""

from __future__ import annotations

import asyncio

import pytest
from conftest import needs_nats
from support import poll_until, running_server
from websockets.asyncio.client import connect as ws_connect
from websockets.exceptions import ConnectionClosed

from posecast.client.bot import BotConfig, run_bot
from posecast.protocol import (
    ClientSession,
    ErrorMessage,
    Hello,
    Join,
    Joined,
    PeerJoined,
    Welcome,
)
from posecast.server.app import ServerConfig

pytestmark = needs_nats


async def _member(url: str, room: str) -> tuple[object, ClientSession, list[object]]:
    """A real websocket client that said hello and joined ``room`` (kept open)."""
    ws = await ws_connect(url)
    session = ClientSession()
    await ws.send(session.send(Hello(agent="holder")))
    session.receive_data(await ws.recv())
    await ws.send(session.send(Join(room=room, streams=("head",), rate=10.0)))
    events: list[object] = []
    while not any(isinstance(e, Joined) for e in events):
        events += session.receive_data(await ws.recv())
    return ws, session, events


async def _peers_heard(ws: object, session: ClientSession, user: int) -> bool:
    """Read ``ws`` until ``user`` joined (True) or a short quiet spell (False)."""
    while True:
        try:
            data = await asyncio.wait_for(ws.recv(), 0.5)  # type: ignore[attr-defined]
        except TimeoutError:
            return False
        if any(isinstance(e, PeerJoined) and e.user == user for e in session.receive_data(data)):
            return True


def _configs(nats_url: str) -> tuple[ServerConfig, ServerConfig]:
    """Node a, whose budget no node with a member meets (its first CPU reading makes
    it full), and node b, with serve's budget."""
    full = ServerConfig(
        host="127.0.0.1",
        port=0,
        cluster=nats_url,
        node="a",
        capacity_cpu=1e-9,
        capacity_min_members=0,
    )
    return full, ServerConfig(host="127.0.0.1", port=0, cluster=nats_url, node="b")


def _bot(urls: tuple[str, ...], room: str) -> BotConfig:
    return BotConfig(
        urls=urls, room=room, rate=20, duration=1.0, methods=("soa",), motion="synthetic:orbit"
    )


async def test_a_full_node_hands_the_client_to_another_node(nats_url: str) -> None:
    full_cfg, free_cfg = _configs(nats_url)
    async with running_server(full_cfg) as full, running_server(free_cfg) as free:
        url_full, url_free = (f"ws://127.0.0.1:{s.port}" for s in (full, free))
        holder, _, _ = await _member(url_full, "r")  # node a owns room r
        cap = full.core.capacity
        await poll_until(lambda: cap.cpu_members > 0 and cap.cpu > 0)
        report = await run_bot(_bot((url_full, url_free), "s"))
        assert report.relay == url_free and report.ending.kind == "complete"
        assert cap.joins_refused == {"server-full": 1}
        # Node b held room s itself (it claimed it: no join forwarded to node a).
        assert free.cluster is not None and free.cluster.joins_forwarded == 0
        assert "s" not in full.rooms
        assert len(full.rooms["r"].members) == 1
        await holder.close()  # type: ignore[attr-defined]


async def test_a_full_nodes_room_refuses_a_join_through_another_node(nats_url: str) -> None:
    full_cfg, free_cfg = _configs(nats_url)
    async with running_server(full_cfg) as full, running_server(free_cfg) as free:
        url_full, url_free = (f"ws://127.0.0.1:{s.port}" for s in (full, free))
        holder, session, _ = await _member(url_full, "r")
        cap = full.core.capacity
        await poll_until(lambda: cap.cpu_members > 0 and cap.cpu > 0)
        ws = await ws_connect(url_free)
        client = ClientSession()
        await ws.send(client.send(Hello(agent="late")))
        (welcome,) = client.receive_data(await ws.recv())
        assert isinstance(welcome, Welcome)  # node b has room: its hello is welcome
        await ws.send(client.send(Join(room="r", streams=("head",), rate=10.0)))
        events = client.receive_data(await ws.recv())
        with pytest.raises(ConnectionClosed):
            await ws.recv()
        (err,) = [e for e in events if isinstance(e, ErrorMessage)]
        assert (err.code, err.in_reply_to, err.fatal) == ("server-full", "join", True)
        assert ws.close_code == 1013
        assert free.cluster is not None and free.cluster.joins_forwarded == 1
        assert cap.joins_refused == {"server-full": 1}
        assert not await _peers_heard(holder, session, welcome.user)
        assert len(full.rooms["r"].members) == 1
        await holder.close()  # type: ignore[attr-defined]
