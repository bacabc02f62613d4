"""Auto rates on a real relay: a narrow emulated link brings a subscriber's rate down and
the client hears it; a fixed rate is served as before, with no rate notice."""

from __future__ import annotations

import asyncio
from collections.abc import Callable

import numpy as np
from support import Pacer, poll_until, running_server

from posecast.client.connection import ClientConnection
from posecast.protocol import RateNotice, SetRate, Snapshot, encode_update
from posecast.scenarios.network import Tier
from posecast.server.app import RelayServer, ServerConfig
from posecast.server.http import metrics_text
from posecast.server.room import Member

POSE = np.tile(np.array([0.0, 1.6, 0.0, 1.0, 0.0, 0.0, 0.0], dtype=np.float32), (3, 1))
STREAMS = ("head", "left", "right")
# 3,000 bytes/s: about 9 Hz of 4-user raw snapshots; the tier's own rate (30) is no cap.
NARROW = Tier("narrow", max_rate_hz=30.0, bandwidth_kbps=24.0, latency_ms=20.0, jitter_ms=2.0,
              loss_pct=0.0)  # fmt: skip


async def _publish(
    conn: ClientConnection, srv: RelayServer, stop: asyncio.Event, pose: np.ndarray = POSE
) -> None:
    """``pose`` (one row per stream) at 30 Hz until ``stop`` is set."""
    assert conn.joined is not None
    ids = np.array(list(conn.joined.streams.values()))
    pacer = Pacer(1 / 30)
    seq = 1
    while not stop.is_set():
        await conn.send_bytes(encode_update(seq, ids, np.full(len(ids), srv.clock()), pose))
        seq = await pacer.next() + 1


async def _session(
    srv: RelayServer, auto: bool, until: Callable[[list[object]], bool]
) -> tuple[ClientConnection, list[object]]:
    """Three publishers and one subscriber (auto or fixed 30 Hz); runs until ``until``
    (a predicate over the subscriber's messages) holds."""
    url = f"ws://127.0.0.1:{srv.port}"
    pubs = [await ClientConnection.open(url, room="a", streams=STREAMS, rate=30) for _ in range(3)]
    sub = await ClientConnection.open(url, room="a", streams=("head",), rate=30, auto_rate=auto)
    got: list[object] = []
    stop = asyncio.Event()

    async def receive() -> None:
        while not stop.is_set():
            got.append((await sub.recv()).event)

    async def drain(conn: ClientConnection) -> None:
        while True:
            await conn.recv()

    async with asyncio.TaskGroup() as tg:
        tasks = [tg.create_task(receive()), *(tg.create_task(drain(p)) for p in pubs)]
        tasks += [tg.create_task(_publish(p, srv, stop)) for p in pubs]
        await poll_until(lambda: until(got), limit=60.0)
        stop.set()
        for t in tasks:
            t.cancel()
    for c in pubs:
        await c.close()
    return sub, got


def _member(srv: RelayServer, user: int) -> Member | None:
    return srv.core.peer_of(user).member


async def test_a_narrow_link_brings_an_auto_rate_down_and_the_client_hears_it() -> None:
    """Auto rate at up to 30 Hz on a 3 kB/s emulated link: the relay chooses a lower
    rate without reading the tier, tells the client (a ``rate`` message), and the
    client's session and the member agree on it."""
    async with running_server(ServerConfig(host="127.0.0.1", port=0, link=NARROW)) as srv:
        sub, got = await _session(
            srv, True, lambda got: any(isinstance(m, RateNotice) and m.rate < 20 for m in got)
        )
        assert sub.joined is not None and sub.joined.rate == 30.0
        notices = [m.rate for m in got if isinstance(m, RateNotice)]
        member = _member(srv, sub.user)
        assert member is not None and member.link_rate is not None
        assert notices[-1] == member.rate == sub.session.rate == member.link_rate.rate
        assert srv.config.min_rate <= member.rate < 20.0
        assert any(isinstance(m, Snapshot) for m in got)
        text = metrics_text(srv.core, srv.clock())
        assert "posecast_auto_rate_members 1" in text
        assert f"posecast_auto_rate_changes_total {len(notices)}" in text
        count = [ln for ln in text.splitlines() if ln.startswith("posecast_auto_rate_hz_count")]
        assert count and int(count[0].split()[1]) >= 1
        await sub.close()


async def test_a_fixed_rate_gets_no_rate_notice_and_keeps_its_link_cap() -> None:
    """A fixed 30 Hz subscriber on the same link: no controller, no ``rate`` message; the
    relay serves it what the link's cap affords, as before auto rates existed."""
    async with running_server(ServerConfig(host="127.0.0.1", port=0, link=NARROW)) as srv:
        sub, got = await _session(
            srv, False, lambda got: sum(isinstance(m, Snapshot) for m in got) >= 30
        )
        member = _member(srv, sub.user)
        assert member is not None and member.link_rate is None
        assert not any(isinstance(m, RateNotice) for m in got)
        assert srv.core.peer_of(sub.user).downlink is not None
        assert member.rate < 30.0  # the link's cap (server.link.EgressLink.rate_for)
        await sub.close()


async def test_set_rate_turns_an_auto_rate_fixed() -> None:
    """An auto-rate client that asks a number with set_rate gets that number, for good."""
    async with running_server(ServerConfig(host="127.0.0.1", port=0)) as srv:
        url = f"ws://127.0.0.1:{srv.port}"
        sub = await ClientConnection.open(url, room="s", streams=("head",), rate=24, auto_rate=True)
        member = _member(srv, sub.user)
        assert member is not None and member.link_rate is not None and member.rate == 24.0
        await sub.send(SetRate(rate=10.0))
        await poll_until(lambda: member.rate == 10.0, limit=30.0)
        assert member.link_rate is None
        await sub.close()


async def test_bots_with_an_auto_rate_follow_the_relays_choice() -> None:
    """Two bots asking auto on a 2 kB/s link (about 14 Hz of their raw snapshots): each
    ends on a rate the relay chose below its ceiling (``BotReport.granted_hz``), and
    their sessions run to the end, fed."""
    from posecast.client.bot import BotConfig
    from posecast.client.swarm import run_bots, swarm_report

    tiny = Tier("tiny", max_rate_hz=30.0, bandwidth_kbps=16.0, latency_ms=20.0, jitter_ms=2.0,
                loss_pct=0.0)  # fmt: skip
    async with running_server(ServerConfig(host="127.0.0.1", port=0, link=tiny)) as srv:
        base = BotConfig(
            url=f"ws://127.0.0.1:{srv.port}",
            room="bots",
            rate=30.0,
            auto_rate=True,
            motion="synthetic:orbit",
            duration=4.0,
            render_rate=10.0,
            methods=("soa",),
            codec="raw",  # compact deltas do not survive an emulated link's skips (yet)
        )
        reports = await run_bots(base, 2)
    assert [r.ending.kind for r in reports] == ["complete", "complete"]
    assert all(r.asked_hz == 30.0 and 5.0 <= r.granted_hz < 30.0 for r in reports)
    rows = swarm_report(reports)["bots"]
    assert all(b["auto_rate"] and b["granted_hz"] < b["asked_hz"] for b in rows)


async def test_a_real_slow_reader_gets_a_lower_auto_rate() -> None:
    """No link emulation: a subscriber whose socket stops reading (tiny receive buffer,
    a client that takes nothing) fills the relay's write buffer; the relay lowers its
    auto rate, and once the client reads again it finds the rate message waiting."""
    import socket

    from websockets.asyncio.client import connect

    from posecast.protocol import ClientSession, Hello, Join, Joined

    streams = tuple(f"s{i}" for i in range(16))
    many = np.tile(POSE[0], (16, 1))
    # No keepalive: a reader that takes nothing would be closed as dead in 5 s.
    config = ServerConfig(host="127.0.0.1", port=0, ping_interval=0)
    async with running_server(config) as srv:
        url = f"ws://127.0.0.1:{srv.port}"
        # 12 x 16 streams: ~7 kB snapshots, so the socket's buffers fill in seconds.
        pubs = [await ClientConnection.open(url, room="slow", streams=streams, rate=5)
                for _ in range(12)]  # fmt: skip
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        sock.setblocking(False)
        await asyncio.get_running_loop().sock_connect(sock, ("127.0.0.1", srv.port))
        session = ClientSession()
        async with connect(url, sock=sock, max_queue=1, ping_interval=None) as ws:
            await ws.send(session.send(Hello(agent="slow")))
            session.receive_data(await ws.recv())
            await ws.send(session.send(Join(room="slow", streams=("head",), rate="auto")))
            got: list[object] = []
            while not any(isinstance(m, Joined) for m in got):
                got += session.receive_data(await ws.recv())
            user = session.user
            assert user is not None
            stop = asyncio.Event()

            async def drain(conn: ClientConnection) -> None:
                while True:
                    await conn.recv()

            async with asyncio.TaskGroup() as tg:
                tasks = [tg.create_task(_publish(p, srv, stop, many)) for p in pubs]
                tasks += [tg.create_task(drain(p)) for p in pubs]
                member = _member(srv, user)
                assert member is not None and member.link_rate is not None
                await poll_until(lambda: member.rate < 30.0, limit=60.0)
                stop.set()
                for t in tasks:
                    t.cancel()
            assert member.link_rate.congestions >= 1
            notices: list[RateNotice] = []
            async with asyncio.timeout(60.0):
                while not notices:
                    notices += [m for m in session.receive_data(await ws.recv())
                                if isinstance(m, RateNotice)]  # fmt: skip
            assert notices[0].rate < 30.0
        for p in pubs:
            await p.close()
