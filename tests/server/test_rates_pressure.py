"""A room that grows past what the relay carries degrades by rate (#28): when the
relay's own ticks run late, its auto-rate subscribers are offered a lower rate (a
``rate`` notice), though their links are wide; fixed-rate subscribers keep their rate
(the relay skips grid points for them, latest wins, never a queue).

A real relay on loopback with real clients, enough of them (``LAG_MIN_MEMBERS``, no
more: the relay admits that many before its first CPU reading) for its lateness to
count as its members' doing; the late ticks are injected into
its capacity's measurements (a real overload needs a busy core, and timing on a
shared machine is not a test), with the relay's clock.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from support import running_server
from test_rates_relay import _member, _session

from posecast.client.connection import ClientConnection
from posecast.protocol import RateNotice, Snapshot
from posecast.server.app import RelayServer, ServerConfig
from posecast.server.capacity import LAG_MIN_MEMBERS
from posecast.server.http import metrics_text


@asynccontextmanager
async def _loaded(srv: RelayServer) -> AsyncIterator[None]:
    """Members that stay in a room of their own, sending nothing: with the session's four
    (three publishers, a subscriber), LAG_MIN_MEMBERS."""
    url = f"ws://127.0.0.1:{srv.port}"
    idle = [
        await ClientConnection.open(url, room="idle", streams=("head",), rate=5)
        for _ in range(LAG_MIN_MEMBERS - 4)
    ]
    try:
        yield
    finally:
        for conn in idle:
            await conn.close()


def _late(srv: RelayServer) -> None:
    """Twenty room ticks, each 200 ms late, as the relay's capacity measures them."""
    cap, now = srv.core.capacity, srv.clock()
    for _ in range(20):
        cap.tick_lag(now, 0.2)


async def test_a_late_relay_offers_its_auto_rate_subscribers_a_lower_rate() -> None:
    async with running_server(ServerConfig(host="127.0.0.1", port=0)) as srv:

        def lowered(got: list[object]) -> bool:
            _late(srv)
            return any(isinstance(m, RateNotice) and m.rate < 30 for m in got)

        async with _loaded(srv):
            sub, got = await _session(srv, True, lowered)
        notices = [m.rate for m in got if isinstance(m, RateNotice)]
        member = _member(srv, sub.user)
        assert member is not None and member.link_rate is not None
        # The client runs at the last rate it heard; the relay may have stepped it again
        # since (down while late, up once it keeps up), so only what was heard is fixed.
        assert notices[-1] == sub.session.rate < 30.0
        assert member.outbox.skips == member.congestion_skips == 0  # the link took all
        text = metrics_text(srv.core, srv.clock())
        (line,) = [ln for ln in text.splitlines() if ln.startswith("posecast_auto_rate_relay_late")]
        assert int(line.split()[1]) >= 1
        await sub.close()


async def test_a_late_relay_tells_a_fixed_rate_subscriber_nothing() -> None:
    async with running_server(ServerConfig(host="127.0.0.1", port=0)) as srv:

        def enough(got: list[object]) -> bool:
            _late(srv)
            return sum(isinstance(m, Snapshot) for m in got) >= 40

        async with _loaded(srv):
            sub, got = await _session(srv, False, enough)
            _late(srv)
            assert srv.core.capacity.overloaded(srv.clock())  # (late throughout)
        member = _member(srv, sub.user)
        assert member is not None and member.link_rate is None and member.rate == 30.0
        assert not any(isinstance(m, RateNotice) for m in got)
        await sub.close()
