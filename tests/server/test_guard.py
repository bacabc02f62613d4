"""Rates across connections (``server/guard.py``): a reconnect does not refill them."""

from __future__ import annotations

from test_core import Client

from posecast.protocol import ErrorMessage, Hello, Join, Joined, UserEvent
from posecast.server.actions import Close
from posecast.server.core import RelayCore
from posecast.server.guard import Guard, GuardLimits, RateTable
from posecast.server.http import metrics_text


def test_a_bucket_refills_at_its_rate_and_forgets_the_oldest_key() -> None:
    """Burst, then one token per 1/rate s; the least recently used key goes first."""
    table = RateTable(rate=2.0, burst=2.0, max_keys=2)
    assert table.take("a", 0.0) and table.take("a", 0.0)
    assert not table.take("a", 0.0) and table.refused == 1
    assert table.take("a", 0.5)
    table.take("b", 0.5)
    table.take("c", 0.5)  # "a" is forgotten (a fresh bucket if it comes back)
    assert len(table) == 2 and table.take("a", 0.5) and table.take("a", 0.5)


def _joiner(core: RelayCore, now: float, address: str) -> Client:
    c = Client(core, core.connect(now, address=address))
    c.send(Hello(agent="j"), now)
    c.read(now)
    c.send(Join(room="r", streams=("head",), rate=10.0), now)
    c.read(now)
    return c


def test_joins_from_one_address_are_limited_across_connections() -> None:
    """A new connection per join does not refill the address's join bucket."""
    core = RelayCore()
    core.handshakes.guard = Guard(GuardLimits(join_rate=1.0, join_burst=3.0))
    joined = []
    for _ in range(5):
        c = _joiner(core, 1.0, "10.0.0.9")
        joined.append(any(isinstance(e, Joined) for e in c.inbox))
        core.disconnect(c.conn, 1.0, said_bye=True)
    assert joined == [True, True, True, False, False]
    metrics = metrics_text(core, 1.0)
    assert 'posecast_joins_refused_total{code="room-full"} 2' in metrics
    other = _joiner(core, 1.0, "10.0.0.10")  # another address has its own bucket
    assert any(isinstance(e, Joined) for e in other.inbox)
    late = _joiner(core, 2.0, "10.0.0.9")  # one token back after a second
    assert any(isinstance(e, Joined) for e in late.inbox)
    refused = [e for e in late.inbox if isinstance(e, ErrorMessage)]
    assert not refused


def test_an_event_flood_over_reconnects_is_closed() -> None:
    """Events over the address's rate: dropped and the connection closed 1008, on
    every new connection until the bucket refills."""
    core = RelayCore()
    core.handshakes.guard = Guard(GuardLimits(event_rate=1.0, event_burst=4.0))
    watcher = _joiner(core, 1.0, "10.0.0.1")
    sent = 0
    for _ in range(2):
        c = _joiner(core, 1.0, "10.0.0.9")
        stream = dict(c.streams)["head"]
        for _ in range(3):
            c.send(UserEvent(kind="button", stream=stream, time=1.0), 1.0)
            sent += 1
        core.disconnect(c.conn, 1.0)
    relayed = [e for e in watcher.read(1.0) if isinstance(e, UserEvent)]
    assert len(relayed) == 4 and sent == 6
    closes = [a for a in c.actions if isinstance(a, Close)]
    assert [a.code for a in closes] == [1008] and "event flood" in closes[0].reason
