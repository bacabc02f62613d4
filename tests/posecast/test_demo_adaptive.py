"""``posecast demo --adaptive``: the bots ask auto rates and the demo shows the rates the
relay chose for each, as the relay itself reports them (``GET /rates``)."""

from __future__ import annotations

import asyncio
import io
import json
import math
from pathlib import Path

import pytest
from support import poll_until, running_server
from typer.testing import CliRunner

from posecast.cli import app
from posecast.client.connection import ClientConnection
from posecast.demo import RateLog, run_demo
from posecast.scenarios.network import Tier

# About 7 Hz of 3-bot raw snapshots; the tier's own rate (30) is no cap for auto rates.
NARROW = Tier("narrow", max_rate_hz=30.0, bandwidth_kbps=24.0, latency_ms=20.0, jitter_ms=2.0,
              loss_pct=0.0)  # fmt: skip


async def test_the_rate_log_reads_what_the_relay_sends_each_member() -> None:
    """A fixed-rate member and an auto-rate one: the log's answer is the relay's own
    rate per member (the room's state), not anything measured at the clients."""
    async with running_server() as server:
        url = f"ws://127.0.0.1:{server.port}"
        fixed = await ClientConnection.open(url, room="r", streams=("head",), rate=12)
        auto = await ClientConnection.open(url, room="r", streams=("head",), rate=25,
                                           auto_rate=True)  # fmt: skip
        log = RateLog(period=0.05)
        async with asyncio.TaskGroup() as tg:
            watch = tg.create_task(log.watch([url], "r"))
            await poll_until(lambda: log.answers >= 2)
            watch.cancel()
        members = server.rooms["r"].members
        assert log.current == {u: m.rate for u, m in members.items()}
        assert sorted(log.current.values()) == [12.0, 25.0]
        bots = [{"id": u} for u in members]
        report = log.report(bots)
        assert report["failures"] == 0 and report["answers"] == log.answers
        assert {b["id"]: b["relay_rate_hz"] for b in bots} == log.current
        for conn in (fixed, auto):
            await conn.close()


async def test_adaptive_demo_on_a_narrow_link_reports_the_relays_choices() -> None:
    """On a link that carries about 7 Hz, the relay brings the auto rates down from 30:
    the report has each bot's rates as the relay answered them, whole Hz within the
    server's range, and the bots heard a lower rate too (their rate messages)."""
    report = await run_demo(bots=3, rate=30.0, auto_rate=True, duration=4.0,
                            methods=("soa",), motion="synthetic:orbit", codec="raw",
                            link=NARROW)  # fmt: skip
    rates = report["rates"]
    assert rates["answers"] >= 2 and rates["source"].startswith("GET /rates?room=demo")
    assert set(rates["users"]) == {str(b["id"]) for b in report["bots"]}
    for b in report["bots"]:
        mine = rates["users"][str(b["id"])]
        assert b["relay_rate_hz"] == mine["now_hz"] and b["relay_mean_hz"] == mine["mean_hz"]
        for hz in (mine["now_hz"], mine["min_hz"], mine["max_hz"]):
            assert 5.0 <= hz <= 30.0 and hz == math.floor(hz)  # the controller's whole Hz
    assert min(u["min_hz"] for u in rates["users"].values()) < 30.0
    assert min(b["granted_hz"] for b in report["bots"]) < 30.0


def test_demo_adaptive_prints_the_relays_rates(tmp_path: Path) -> None:
    """``demo --adaptive``: an auto rate up to 30 Hz; the bots table has the chosen and
    relay-mean columns with the report's values, and the verdict names auto rates."""
    out = tmp_path / "demo.json"
    res = CliRunner().invoke(app, [
        "demo", "--adaptive", "--bots", "2", "--duration", "3", "--motion", "synthetic:orbit",
        "--interp", "soa", "--no-record", "--json", str(out),
    ])  # fmt: skip
    assert res.exit_code == 0, res.output
    report = json.loads(out.read_text())
    assert report["server"]["auto_rate"] and report["server"]["rate_hz"] == 30.0
    assert "an auto rate (up to 30 Hz)" in res.output
    assert "relay" in res.output and "mean Hz" in res.output and "relay mean: " in res.output
    for b in report["bots"]:
        row = next(line.split() for line in res.output.splitlines()
                   if line.split()[:2] == [str(b["id"]), b["name"]])  # fmt: skip
        assert row[2:4] == [f"{b['granted_hz']:.1f}", f"{b['relay_mean_hz']:.1f}"], row
    assert "verdict: at the rates the relay chose (mean " in res.output


def test_adaptive_and_link_mistakes_are_one_line() -> None:
    """An unknown tier, and --link with --nodes, are refused before anything runs."""
    res = CliRunner().invoke(app, ["demo", "--adaptive", "--link", "dialup"])
    assert res.exit_code == 2 and "unknown tier 'dialup'" in res.output
    res = CliRunner().invoke(app, ["demo", "--link", "poor", "--nodes", "2"])
    assert res.exit_code == 2 and "--link emulates the demo's one relay" in res.output


async def test_a_budget_adds_each_peers_rate_as_the_relay_chose_it() -> None:
    """``budget_deg``: the relay answers each peer's rate to each bot (``/rates``
    ``peers``); the report has, per bot, every other bot's mean rate, within the
    server's range and at most the bot's own snapshot rate."""
    report = await run_demo(bots=3, rate=30.0, auto_rate=True, duration=4.0,
                            methods=("soa",), motion="synthetic:orbit",
                            budget_deg=0.5, spawn="circle")  # fmt: skip
    assert report["server"]["budget_deg"] == 0.5
    ids = {str(b["id"]) for b in report["bots"]}
    for b in report["bots"]:
        peers = b["relay_peer_mean_hz"]
        assert ids - {str(b["id"])} <= set(peers)
        assert all(5.0 <= r <= b["relay_mean_hz"] + 1e-9 for r in peers.values()), peers
        assert report["rates"]["users"][str(b["id"])]["peers_mean_hz"] == peers


def test_the_per_peer_table_fits_80_columns(monkeypatch: pytest.MonkeyPatch) -> None:
    """The per-peer rates print one column a peer (up to 8), else lowest/mean/highest."""
    from rich.console import Console

    from posecast.cli import common, report

    out = io.StringIO()
    narrow = Console(file=out, width=80, force_terminal=False)
    monkeypatch.setattr(common, "console", narrow)
    monkeypatch.setattr(report, "console", narrow)
    for n in (3, 12):
        rates = {str(p): 5.0 + p for p in range(n)}
        bots = [{"id": i, "name": f"bot{i}", "relay_peer_mean_hz": rates} for i in range(n)]
        out.seek(0)
        out.truncate(0)
        report._print_peer_rates({"bots": bots})
        text = out.getvalue()
        assert max(len(line) for line in text.splitlines()) <= 80, text
        assert ("lowest" in text) == (n > 8), text
        assert ("16.0" if n > 8 else "7.0") in text, text
