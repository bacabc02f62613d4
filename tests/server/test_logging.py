"""What the relay logs: bounded under a misbehaving peer, quiet for probes and scrapes.

A server runs for weeks with a metrics scraper and a health probe polling it,
and sometimes with a broken or hostile client: neither may turn into one log
line per request or per bad frame.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable
from typing import Any

import pytest
from relaykit import joined_raw, settle, update_bytes
from test_http import http_get
from websockets.exceptions import ConnectionClosed

from posecast.server.app import LogLimiter, RelayServer, ServerConfig, serving

ServerFactory = Callable[..., Any]

NAN_POSE = [[float("nan"), 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0]]


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def url_of(srv: RelayServer) -> str:
    return f"ws://127.0.0.1:{srv.port}"


def protocol_errors(srv: RelayServer) -> int:
    """Protocol errors of the open connections."""
    stats: list[Any] = srv.statistics()["connection_stats"]  # type: ignore[assignment]
    return sum(c.protocol_errors for c in stats)


# -- the limiter, on a fake clock ----------------------------------------------------------


def test_limiter_logs_the_first_then_holds_back_within_the_interval() -> None:
    """The first record goes through; the rest of the interval is only counted."""
    clock = FakeClock()
    lim = LogLimiter(1.0, clock)
    assert lim.admit() == 0
    assert lim.note(0) == ""
    for _ in range(1234):
        clock.now += 0.0005
        assert lim.admit() is None
    assert lim.suppressed == 1234


def test_limiter_reports_the_count_held_back_with_the_next_record() -> None:
    """After the interval the next record goes through with the count and the span."""
    clock = FakeClock()
    lim = LogLimiter(1.0, clock)
    lim.admit()
    clock.now += 0.25
    for _ in range(1234):
        assert lim.admit() is None
    clock.now += 0.75
    held = lim.admit()
    assert held == 1234
    assert lim.note(held) == " (and 1234 more in the last 1.0 s)"
    # The count restarts: a quiet interval, then one record, mentions nothing held back.
    clock.now += 5.0
    assert lim.admit() == 0


def test_limiter_span_is_the_time_since_the_previous_record() -> None:
    """Held-back records after a long pause are counted over the whole time since."""
    clock = FakeClock()
    lim = LogLimiter(2.0, clock)
    lim.admit()
    clock.now += 0.5
    lim.admit()
    clock.now += 2.5
    held = lim.admit()
    assert held == 1
    assert lim.note(held) == " (and 1 more in the last 3.0 s)"


def test_limiter_flush_hands_over_what_is_still_held_back() -> None:
    """flush() returns the records never mentioned (e.g. at close) and restarts the count."""
    clock = FakeClock()
    lim = LogLimiter(1.0, clock)
    assert lim.flush() == 0
    lim.admit()
    for _ in range(7):
        clock.now += 0.01
        lim.admit()
    assert lim.flush() == 7
    assert lim.span == pytest.approx(0.07)
    assert lim.flush() == 0


def test_limiter_with_zero_interval_logs_everything() -> None:
    clock = FakeClock()
    lim = LogLimiter(0.0, clock)
    assert [lim.admit() for _ in range(3)] == [0, 0, 0]
    with pytest.raises(ValueError, match="interval"):
        LogLimiter(-1.0, clock)


# -- a real relay ------------------------------------------------------------------------------


def _records(caplog: pytest.LogCaptureFixture, text: str) -> list[logging.LogRecord]:
    return [r for r in caplog.records if text in r.getMessage()]


async def test_thousands_of_bad_frames_make_a_handful_of_log_lines(
    server_factory: ServerFactory, caplog: pytest.LogCaptureFixture
) -> None:
    """3000 bad poses from one peer: one line for the first, one with the count at close."""
    caplog.set_level(logging.INFO)
    # An interval longer than the test: the count of lines does not depend on its speed.
    # No misbehaviour budget: this is about logging, not closing.
    cfg = ServerConfig(host="127.0.0.1", port=0, peer_log_interval=3600.0, misbehaviour_burst=0)
    n = 3000
    async with server_factory(cfg) as srv:
        ws, user, ids = await joined_raw(url_of(srv), "r")
        caplog.clear()

        async def drain() -> None:  # read the error replies, so the peer is never "too slow"
            with contextlib.suppress(ConnectionClosed):
                async for _ in ws:
                    pass

        reader = asyncio.create_task(drain())
        for seq in range(n):
            await ws.send(update_bytes(ids, NAN_POSE, seq, srv.clock()))
            if seq % 100 == 0:
                await asyncio.sleep(0)
        await settle(lambda: protocol_errors(srv) >= n)
        await ws.close()
        await reader
        await settle(lambda: srv.closed_connections == 1)
    bad = _records(caplog, "bad-pose")
    assert len(bad) == 1, [r.getMessage() for r in bad]
    assert bad[0].levelno == logging.INFO and f"user {user}:" in bad[0].getMessage()
    (held,) = _records(caplog, "not logged")
    assert f"user {user}: {n - 1} more of its errors not logged" in held.getMessage()
    mine = [r for r in caplog.records if r.name.startswith(("posecast", "websockets"))]
    assert len(mine) <= 10, [r.getMessage() for r in mine]


async def test_bad_frames_are_logged_once_per_interval_with_the_count(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """On the server's (fake) clock: one line per interval, naming how many were held back."""
    caplog.set_level(logging.INFO)
    clock = FakeClock()
    # No misbehaviour budget: this is about logging, not closing.
    cfg = ServerConfig(host="127.0.0.1", port=0, peer_log_interval=1.0, misbehaviour_burst=0)
    async with serving(RelayServer(cfg, clock=clock)) as srv:
        ws, _, ids = await joined_raw(url_of(srv), "r")
        for burst in range(3):
            for seq in range(500):
                await ws.send(update_bytes(ids, NAN_POSE, seq, clock()))
            total = 500 * (burst + 1)
            await settle(lambda t=total: protocol_errors(srv) >= t)
            clock.now += 1.0
        await ws.close()
        await settle(lambda: srv.closed_connections == 1)
    lines = [r.getMessage() for r in _records(caplog, "bad-pose")]
    assert len(lines) == 3, lines
    assert lines[0].endswith("(bad-pose)")
    assert lines[1].endswith("(bad-pose) (and 499 more in the last 1.0 s)")
    assert lines[2].endswith("(bad-pose) (and 499 more in the last 1.0 s)")
    assert len(_records(caplog, "499 more of its errors not logged")) == 1


async def test_metrics_and_health_scrapes_log_nothing_at_info(
    server_factory: ServerFactory, caplog: pytest.LogCaptureFixture
) -> None:
    """/metrics and /healthz (and a rejected handshake) are DEBUG; websockets still INFO."""
    caplog.set_level(logging.INFO)
    caplog.set_level(logging.DEBUG, logger="websockets.server")  # last: the handler's level
    async with server_factory() as srv:
        caplog.clear()
        for path in ("/metrics", "/healthz", "/metrics?x=1", "/"):
            await http_get(srv.port, path)
        # "connection closed" (websockets 17) or "= connection is CLOSED" (16).
        await settle(
            lambda: (
                len(_records(caplog, "connection closed"))
                + len(_records(caplog, "connection is CLOSED"))
                >= 4
            )
        )
        http = list(caplog.records)
        caplog.clear()
        ws, _, _ = await joined_raw(url_of(srv), "r")
        await ws.close()
        await settle(lambda: srv.closed_connections == 1)
        socket_records = list(caplog.records)
    assert [r for r in http if r.levelno >= logging.INFO] == []
    # websockets 17 says "HTTP response sent", 16 "connection rejected" (viser pins < 17).
    sent = [
        r.getMessage()
        for r in http
        if r.getMessage().startswith(("HTTP response sent", "connection rejected"))
    ]
    # Three 200s, unless viser ran in this process before: it filters "connection
    # rejected (200 OK)" out of the websockets.server logger for good.
    assert sum(m.endswith("(200 OK)") for m in sent) in (0, 3)
    assert sum(m.endswith("(426 Upgrade Required)") for m in sent) == 1
    # A websocket's own open and close are still reported at INFO.
    opened = [r for r in socket_records if r.getMessage() == "connection open"]
    assert [r.levelno for r in opened] == [logging.INFO]
