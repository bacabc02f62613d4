"""HTTP on the websocket port: GET /healthz and GET /metrics (Prometheus text format)."""

from __future__ import annotations

import asyncio
import re
import urllib.request
from collections.abc import Callable
from typing import Any

import pytest
from relaykit import Bot, settle
from test_core import connect

from posecast.protocol import PoseUpdate
from posecast.server.app import RelayServer, ServerConfig
from posecast.server.core import RelayCore
from posecast.server.http import metrics_text

ServerFactory = Callable[..., Any]

# One sample line of the text exposition format: name, optional labels, value.
SAMPLE = re.compile(
    r'^(?P<name>[a-zA-Z_:][a-zA-Z0-9_:]*)(?P<labels>\{(?:[a-zA-Z_]\w*="(?:[^"\\]|\\.)*",?)*\})?'
    r" (?P<value>-?[0-9.]+(?:e[+-]?[0-9]+)?|NaN|[+-]Inf)$"
)


async def http_get(port: int, path: str) -> tuple[int, dict[str, str], str]:
    """A raw HTTP/1.1 GET: status, headers (lowercase names) and body."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nUser-Agent: test\r\n\r\n".encode())
    await writer.drain()
    async with asyncio.timeout(10):
        data = await reader.read()  # the server closes after one response
    writer.close()
    await writer.wait_closed()
    head, _, body = data.partition(b"\r\n\r\n")
    status_line, *header_lines = head.decode("latin-1").split("\r\n")
    headers = {}
    for line in header_lines:
        name, _, value = line.partition(":")
        headers[name.strip().lower()] = value.strip()
    assert int(headers["content-length"]) == len(body)
    return int(status_line.split()[1]), headers, body.decode()


def parse_metrics(text: str) -> dict[str, dict[str, float]]:
    """name -> {labels: value}; asserts every line is valid exposition text."""
    assert text.endswith("\n")
    samples: dict[str, dict[str, float]] = {}
    typed: set[str] = set()
    for line in text.splitlines():
        if line.startswith("# HELP "):
            continue
        if line.startswith("# TYPE "):
            _, _, name, kind = line.split(" ")
            assert kind in ("counter", "gauge", "histogram"), line
            if kind == "counter":
                assert name.endswith("_total"), line
            if kind == "histogram":
                typed.update(name + part for part in ("_bucket", "_sum", "_count"))
            else:
                typed.add(name)
            continue
        m = SAMPLE.match(line)
        assert m is not None, f"not a sample line: {line!r}"
        assert m["name"] in typed, f"sample before its TYPE: {line!r}"
        samples.setdefault(m["name"], {})[m["labels"] or ""] = float(m["value"])
    return samples


def url_of(srv: RelayServer) -> str:
    return f"ws://127.0.0.1:{srv.port}"


async def test_healthz_ok(server_factory: ServerFactory) -> None:
    """GET /healthz answers 200 with body "ok"."""
    async with server_factory() as srv:
        status, headers, body = await http_get(srv.port, "/healthz")
        assert status == 200
        assert body.strip() == "ok"
        assert headers["content-type"].startswith("text/plain")


async def test_healthz_with_standard_client(server_factory: ServerFactory) -> None:
    """urllib (what probes and scripts use) gets 200 "ok" from /healthz."""
    async with server_factory() as srv:

        def fetch() -> tuple[int, bytes]:
            with urllib.request.urlopen(f"http://127.0.0.1:{srv.port}/healthz", timeout=10) as r:
                return r.status, r.read()

        status, body = await asyncio.to_thread(fetch)
        assert (status, body.strip()) == (200, b"ok")


async def test_metrics_prometheus_text(server_factory: ServerFactory) -> None:
    """GET /metrics is valid Prometheus text with the connection, room and traffic figures."""
    async with server_factory() as srv:
        status, headers, body = await http_get(srv.port, "/metrics")
        assert status == 200
        assert headers["content-type"].startswith("text/plain; version=0.0.4")
        empty = parse_metrics(body)
        assert empty["posecast_connections"] == {"": 0.0}
        assert empty["posecast_rooms"] == {"": 0.0}
        pub = await Bot.join(url_of(srv), srv.clock, room="lab", rate=20.0, seed=1)
        sub = await Bot.join(url_of(srv), srv.clock, room="lab", rate=10.0, streams=("head",))
        async with pub.running(), sub.running(publish=False):
            await settle(lambda: len(sub.snapshots) >= 3)
            _, _, body = await http_get(srv.port, "/metrics?probe=1")
        m = parse_metrics(body)
        assert m["posecast_connections"] == {"": 2.0}
        assert m["posecast_rooms"] == {"": 1.0}
        assert m["posecast_room_members"] == {'{room="lab"}': 2.0}
        assert m["posecast_room_poses_out_total"]['{room="lab"}'] > 0
        assert m["posecast_frames_in_total"][""] > 0
        assert m["posecast_bytes_out_total"][""] > m["posecast_frames_out_total"][""] > 0
        for name in ("posecast_flood_drops_total", "posecast_snapshot_skips_total"):
            assert m[name] == {"": 0.0}
        await pub.conn.close()
        await sub.conn.close()


async def test_metrics_counters_survive_closed_connections(server_factory: ServerFactory) -> None:
    """Counters never go down: a closed connection's traffic and drops stay counted."""
    cfg = ServerConfig(host="127.0.0.1", port=0, max_update_rate=30.0)
    async with server_factory(cfg) as srv:
        bot = await Bot.join(url_of(srv), srv.clock, room="lab", rate=10.0)
        async with bot.running(publish=False):
            ids = bot.stream_ids
            pose = [[0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0]] * len(ids)
            for seq in range(80):  # a burst beyond the 30-token bucket
                await bot.conn.send(PoseUpdate.from_arrays(seq, ids, [srv.clock()] * 3, pose))
            await settle(
                lambda: parse_metrics(srv.metrics_text())["posecast_frames_in_total"][""] > 80
            )
            live = parse_metrics(srv.metrics_text())
            assert live["posecast_flood_drops_total"][""] >= 80 - 31
        await bot.conn.close()
        await settle(lambda: srv.statistics()["connections"] == 0)
        _, _, body = await http_get(srv.port, "/metrics")
        after = parse_metrics(body)
        assert after["posecast_connections"] == {"": 0.0}
        assert after["posecast_connections_closed_total"][""] >= 1
        for name in ("posecast_flood_drops_total", "posecast_frames_in_total"):
            assert after[name][""] >= live[name][""], name


async def test_metrics_escape_room_labels(server_factory: ServerFactory) -> None:
    """A room name with quotes and backslashes stays one valid label value.

    (A newline is escaped too, but no room name holds one: ``bad-room``.)
    """
    async with server_factory() as srv:
        room = 'a "quoted"\\room name'
        bot = await Bot.join(url_of(srv), srv.clock, room=room, rate=10.0)
        _, _, body = await http_get(srv.port, "/metrics")
        m = parse_metrics(body)
        assert m["posecast_room_members"] == {'{room="a \\"quoted\\"\\\\room name"}': 1.0}
        await bot.conn.close()


async def test_metric_values_exact(server_factory: ServerFactory) -> None:
    """Large counters are printed exactly, not rounded to six digits."""
    async with server_factory() as srv:
        srv.totals["bytes_in"] = 1_234_567_891
        m = parse_metrics(srv.metrics_text())
        assert m["posecast_bytes_in_total"][""] == 1_234_567_891


async def test_other_paths_are_not_http_endpoints(server_factory: ServerFactory) -> None:
    """Any other plain GET is not served (it is a websocket endpoint): no 200."""
    async with server_factory() as srv:
        status, _, _ = await http_get(srv.port, "/nope")
        assert status != 200


def test_tick_overdue_is_measured_from_the_due_time() -> None:
    """/metrics reports how late the earliest due tick is at scrape time: 0 when on
    time, the true delay when the relay has not got round to it (never NaN)."""
    core = RelayCore()
    assert "posecast_tick_overdue_seconds 0" in metrics_text(core, 5.0)  # no room at all
    connect(core, 1.0)
    due = core.next_deadline()
    assert due is not None
    assert "posecast_tick_overdue_seconds 0" in metrics_text(core, due - 0.01)
    text = metrics_text(core, due + 0.75)
    (line,) = [ln for ln in text.splitlines() if ln.startswith("posecast_tick_overdue_seconds")]
    assert float(line.split()[1]) == pytest.approx(0.75)
    assert "posecast_tick_overdue_seconds" not in metrics_text(core)  # no clock, no gauge
