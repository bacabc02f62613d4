"""``bench relay`` accounts for every join: admitted, refused by code, hung, unreachable.

The load's own client (``posecast.bench.load``) against real sockets: a relay with
room, a relay whose measured budget is spent (``server-full``), a listener that
never answers (hung), and a port nobody listens on; then the controller's merge
and the report's figures.
"""

from __future__ import annotations

import asyncio
import math
import socket
from typing import Any

from support import poll_until, running_server

from posecast.bench.fleet import join_figures, merge_parts, merge_ramped
from posecast.bench.load import join_outcomes, measured_clients
from posecast.bench.loadclient import HUNG, JOINED, UNREACHABLE, _BenchClient, _LoadStats
from posecast.server.app import ServerConfig

TINY = ServerConfig(host="127.0.0.1", port=0, capacity_cpu=1e-9, capacity_min_members=0)


async def _outcomes() -> dict[str, Any]:
    stats = _LoadStats(5)

    def client(i: int) -> _BenchClient:
        return _BenchClient(i, "r", 20.0, stats, "compact")

    clients = [client(i) for i in range(5)]
    async with running_server() as free, running_server(TINY) as full:
        await clients[0].open(f"ws://127.0.0.1:{free.port}", 5.0)
        holder = client(4)  # the full relay's one member (not counted below)
        await holder.open(f"ws://127.0.0.1:{full.port}", 5.0)
        cap = full.core.capacity
        await poll_until(lambda: cap.cpu_members > 0 and cap.cpu > 0)
        await clients[1].open(f"ws://127.0.0.1:{full.port}", 5.0)
        # A listener that takes the connection and never answers its handshake.
        taken: list[asyncio.StreamWriter] = []

        async def take(_r: asyncio.StreamReader, w: asyncio.StreamWriter) -> None:
            taken.append(w)

        mute = await asyncio.start_server(take, "127.0.0.1", 0)
        mute_port = mute.sockets[0].getsockname()[1]
        await clients[2].open(f"ws://127.0.0.1:{mute_port}", 0.3)
        for w in taken:
            w.close()
        mute.close()
        await mute.wait_closed()
        with socket.socket() as s:  # a port nobody listens on (bound, never listening)
            s.bind(("127.0.0.1", 0))
            await clients[3].open(f"ws://127.0.0.1:{s.getsockname()[1]}", 2.0)
        ramped = join_outcomes(clients[:4])
        for c in (clients[0], holder):
            assert c.conn is not None
            c.conn.abort()
    return ramped


def test_every_join_is_accounted_for() -> None:
    """joined, server-full (with its time), hung and unreachable, and the report's keys."""
    ramped = asyncio.run(_outcomes())
    assert ramped["joined"] == 1 and ramped["failed"] == 3
    assert ramped["codes"] == {"server-full": 1, HUNG: 1, UNREACHABLE: 1}
    assert ramped["hung"] == 1
    assert ramped["hung_at"] == {"upgrade": 1}  # the mute listener took the connection
    assert len(ramped["join_s"]) == 1 and len(ramped["refused_s"]) == 2
    assert len(ramped["server_full_s"]) == 1
    # Every client that reached a listener was connected; three got their upgrade.
    assert len(ramped["connect_s"]) == 3 and len(ramped["upgrade_s"]) == 2
    assert all(t >= 0 for t in ramped["join_s"] + ramped["refused_s"])
    two = merge_ramped([{**ramped, "ramp_s": 1.0}, {**ramped, "ramp_s": 2.0}])
    assert two["codes"] == {"server-full": 2, HUNG: 2, UNREACHABLE: 2} and two["hung"] == 2
    figures = join_figures(two)
    assert figures["clients_joined"] == 2 and figures["clients_failed"] == 6
    assert figures["join_errors"] == {"server-full": 2, UNREACHABLE: 2}
    assert figures["clients_hung"] == 2 and figures["clients_refused"] == 2
    assert figures["clients_hung_at"] == {"upgrade": 2}
    assert figures["server_full_within_1s"] + (figures["server_full_max_ms"] > 1e3) >= 1
    for key in ("server_full_p99_ms", "connect_p99_ms", "upgrade_p99_ms"):
        assert math.isfinite(figures[key]) and figures[key] >= 0, key
    assert math.isfinite(figures["refusal_p99_ms"]) and math.isfinite(figures["join_p99_ms"])
    assert any("server-full" in e for e in figures["join_error_examples"])


def test_refused_clients_are_not_counted_as_clients_without_snapshots() -> None:
    """Per-client snapshot figures are over the clients that joined."""
    stats = _LoadStats(4)
    stats.t0, stats.t1 = 0.0, 2.0
    for i in (0, 1):
        for k in range(40):
            stats.snapshot(i, 0.05 * k, 0.05 * k, 0.05 * k, 100, 3, 0)
    counts = stats.counts([0, 1])
    assert counts["clients_measured"] == 2 and counts["clients_without_snapshots"] == 0
    assert counts["snapshots_per_client_s_min"] == 20.0
    everyone = stats.counts()
    assert everyone["clients_without_snapshots"] == 2
    part = {
        **counts,
        "load_clients": 4,
        "close_reasons": [],
        "server_errors": {},
        "server_error_examples": {},
    }
    merged = merge_parts([part])
    assert merged["snapshots_per_client_s"] == 20.0


def test_a_member_alone_in_its_room_is_not_measured() -> None:
    """Refusals can leave a member alone in its room: it is sent nothing, so the
    snapshot rate is measured over members that have a room mate."""
    stats = _LoadStats(5)
    clients = [_BenchClient(i, f"room-{i // 3}", 20.0, stats, "compact") for i in range(5)]
    for c, outcome in zip(clients, [JOINED, JOINED, "server-full", JOINED, HUNG], strict=True):
        c.outcome = outcome
    assert measured_clients(clients) == [0, 1]


def test_a_shed_run_accounts_for_every_client_and_reads_the_storm() -> None:
    """``--shed`` end to end: the relay under test keeps its capacity budget (serve's
    defaults), every client is joined, refused or hung, none hangs, and the report
    reads the join storm from the relay's /metrics (its members' tick lag meanwhile)."""
    import io

    from rich.console import Console

    from posecast.bench import run_relay_bench
    from posecast.protocol import codec

    out = Console(file=io.StringIO(), width=200)
    report = run_relay_bench(24, 6, 20.0, 1.0, shed=True, console=out, warmup=0.5, ramp_rate=100.0)
    assert report["shed"] and report["metrics_ok"] and report["server_exit_code"] == 0
    joined, refused, hung = (
        report[k] for k in ("clients_joined", "clients_refused", "clients_hung")
    )
    assert joined + refused + hung == 24 and hung == 0 and joined >= 16
    assert set(report["join_errors"]) <= {"server-full"}
    assert "ramp_tick_lag_p99_ms" in report and report["join_cpu_ms_per_client"] >= 0
    assert report["ticks_per_client_s"] >= report["snapshots_per_client_s"] > 0
    assert report["codec_implementation"] == codec.IMPLEMENTATION
