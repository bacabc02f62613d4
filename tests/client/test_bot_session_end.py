"""A bot whose server goes away mid-session: it reports what it had and says how it ended.

Real relays on loopback: in process (stopped gracefully, or every connection
aborted under the bots), and ``posecast serve`` as a subprocess (SIGTERM, SIGKILL)
against ``posecast bots`` as a subprocess, for the exit code and the output.
"""

from __future__ import annotations

import asyncio
import os
import re
import signal
import subprocess
import sys
import urllib.request
from pathlib import Path

import pytest
from support import poll_until, relayed, running_server, wait_until

from posecast.client.bot import BotConfig, BotReport, SessionEnd, run_bot
from posecast.client.swarm import session_ending, swarm_report

#: Far longer than any test waits: a session only ends early here.
LONG = 120.0


async def _session_ended_by(end: str) -> list[BotReport]:
    """Two bots in a long session; once poses flow, the server ends it ``end``-ly."""
    async with running_server() as server:
        url = f"ws://127.0.0.1:{server.port}"
        cfgs = [
            # resume=False: a dropped connection ends the session here (bots that
            # resume are tests/client/test_bot_resume.py's).
            BotConfig(
                url=url, room="gone", motion="synthetic:orbit", seed=i, duration=LONG, resume=False
            )
            for i in range(2)
        ]
        async with asyncio.TaskGroup() as tg:
            tasks = [tg.create_task(run_bot(c)) for c in cfgs]
            # Both bots joined and each got a good number of the other's poses.
            await poll_until(lambda: relayed(server, "gone") >= 2 * 3 * 20)
            if end == "stop":
                server.stop()
            else:  # no close frame: the sockets just break under the bots
                for user in list(server.rooms["gone"].members):
                    server.connection_of(user).ws.transport.abort()
    return [t.result() for t in tasks]


def _check_report_covers_the_session(reports: list[BotReport]) -> None:
    for rep in reports:
        assert rep.frames_rendered > 0
        assert len(rep.streams) == 3  # the other bot's head and hands
        assert rep.poses_received >= 20
        assert 0 < rep.duration < LONG
        assert rep.ending.after_s < LONG
    report = swarm_report(reports)
    for classes in report["methods"].values():
        assert set(classes) == {"hands", "head"}


def test_graceful_server_shutdown_ends_the_session_with_a_report() -> None:
    reports = asyncio.run(_session_ended_by("stop"))
    _check_report_covers_the_session(reports)
    for rep in reports:
        assert rep.ending.kind == "closed"
        assert (rep.ending.code, rep.ending.reason) == (1001, "going away")
        assert rep.ending.graceful
        assert rep.ending.describe().startswith("server closed: going away (1001) after ")
    lines, code = session_ending(reports)
    assert code == 0
    assert len(lines) == 1
    assert re.fullmatch(
        r"session ended early: server closed: going away \(1001\) after \d+\.\d s "
        r"\(2 of 2 bots\); the report covers that time",
        lines[0],
    )


def test_lost_connection_ends_the_session_with_a_report() -> None:
    reports = asyncio.run(_session_ended_by("abort"))
    _check_report_covers_the_session(reports)
    for rep in reports:
        assert rep.ending.kind == "lost"
        assert rep.ending.code is None
        assert not rep.ending.graceful
        assert re.fullmatch(r"connection lost after \d+\.\d s", rep.ending.describe())
    lines, code = session_ending(reports)
    assert code == 1
    assert len(lines) == 1 and lines[0].startswith("session ended early: connection lost after ")
    report = swarm_report(reports)
    assert report["ending"] == {"complete": False, "lines": lines, "exit_code": 1}
    assert all(b["ended"].startswith("connection lost after ") for b in report["bots"])


def _ending(kind: str, code: int | None = None, after: float = 2.0) -> SessionEnd:
    return SessionEnd(kind, after, code, "going away" if code == 1001 else "x")  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("endings", "code"),
    [
        (["complete", "complete"], 0),
        (["complete", ("closed", 1001)], 0),
        (["complete", ("closed", 1000)], 0),
        ([("closed", 1011), "complete"], 1),
        (["complete", "lost"], 1),
        ([("closed", 1001), "lost"], 1),
    ],
)
def test_exit_code_is_0_unless_lost_or_closed_for_an_error(
    endings: list[str | tuple[str, int]], code: int
) -> None:
    reports = []
    for i, e in enumerate(endings):
        kind, close = (e, None) if isinstance(e, str) else e
        reports.append(
            BotReport(
                user=i,
                name=f"b{i}",
                qoe={},
                rate_hz=10.0,
                delay_ms=100.0,
                render_stall_fraction=0.0,
                frames_rendered=90,
                render_cpu_s=0.0,
                snapshot_bytes=0,
                poses_received=0,
                bytes_in=0,
                bytes_out=0,
                duration=1.0,
                clock_rtt_ms=0.1,
                ending=_ending(kind, close),
            )
        )
    lines, got = session_ending(reports)
    assert got == code
    # One line per way of ending early, none when every bot completed.
    early = {(r.ending.kind, r.ending.code) for r in reports if r.ending.kind != "complete"}
    assert len(lines) == len(early)


# -- the CLI, as a user runs it -----------------------------------------------------------


def _serve() -> tuple[subprocess.Popen[str], int]:
    server = subprocess.Popen(
        [sys.executable, "-m", "posecast.cli", "serve", "--port", "0", "--log-level", "warning"],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    assert server.stdout is not None
    line = server.stdout.readline()
    found = re.search(r"ws://[^:]+:(\d+)", line)
    assert found, line
    return server, int(found.group(1))


def _metric(port: int, name: str) -> float:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=30) as resp:
        text = resp.read().decode()
    found = re.search(rf"^{name} (\S+)$", text, re.M)
    return float(found.group(1)) if found else 0.0


def _bots_until_the_server(sig: signal.Signals, tmp: Path) -> tuple[int, str]:
    """``posecast bots`` (2 bots, a long session) against ``posecast serve``; once
    snapshots flow the server gets ``sig``. Returns the bots' exit code and output."""
    server, port = _serve()
    bots = None
    try:
        bots = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "posecast.cli",
                "bots",
                "--url",
                f"ws://127.0.0.1:{port}",
                "--n",
                "2",
                "--motion",
                "synthetic",
                "--duration",
                str(LONG),
                "--json",
                str(tmp / "bots.json"),
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1", "COLUMNS": "200"},
        )

        def flowing() -> bool:
            assert bots.poll() is None
            return _metric(port, "posecast_frames_out_total") >= 100

        wait_until(flowing, every=0.05)  # 60 s: a hang guard
        server.send_signal(sig)
        server.wait(30)
        out, _ = bots.communicate(timeout=120)
        return bots.returncode, out
    finally:
        for proc in (bots, server):
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait(10)
        if server.stdout is not None:
            server.stdout.close()


def _check_cli_output(out: str) -> None:
    assert "Traceback" not in out
    assert "cannot connect" not in out
    assert "wire:" in out  # the report for the time it had


def test_bots_cli_exits_0_when_the_server_shuts_down(tmp_path: Path) -> None:
    code, out = _bots_until_the_server(signal.SIGTERM, tmp_path)
    assert code == 0, out
    _check_cli_output(out)
    assert re.search(
        r"session ended early: server closed: going away \(1001\) after \d+\.\d s "
        r"\(2 of 2 bots\)",
        out,
    ), out


def test_bots_cli_exits_1_when_the_connection_is_lost(tmp_path: Path) -> None:
    import json

    code, out = _bots_until_the_server(signal.SIGKILL, tmp_path)
    assert code == 1, out
    _check_cli_output(out)
    assert re.search(r"session ended early: connection lost after \d+\.\d s \(2 of 2 bots\)", out)
    report = json.loads((tmp_path / "bots.json").read_text())
    assert report["ending"]["exit_code"] == 1 and not report["ending"]["complete"]
