"""Ctrl-C ends a run early and its report covers the time run.

In process: ``run_bots(stop=...)`` ends every bot's session when the event is set;
with the real executable: SIGINT to ``posecast demo`` and ``posecast bots`` prints
the report of the time run, says it was interrupted, and exits 130.
"""

from __future__ import annotations

import asyncio
import os
import re
import selectors
import signal
import subprocess
import sys
import urllib.request
from collections.abc import Callable
from pathlib import Path

from support import poll_until, running_server, wait_until

from posecast.client.bot import BotConfig
from posecast.client.swarm import run_bots, swarm_report


async def test_setting_stop_ends_every_bot_and_reports_the_time_run() -> None:
    """Bots asked for 600 s end when ``stop`` is set; each says interrupted, with QoE."""
    async with running_server() as server:
        stop = asyncio.Event()
        base = BotConfig(url=f"ws://127.0.0.1:{server.port}", room="r", motion="synthetic:orbit",
                         duration=600.0, methods=("soa",), name="bot")  # fmt: skip
        run = asyncio.create_task(run_bots(base, 2, stop=stop))
        room = lambda: server.statistics()["rooms"].get("r")  # noqa: E731
        await poll_until(lambda: room() is not None and room().poses_out > 60)
        stop.set()
        reports = await asyncio.wait_for(run, 120)  # a hang guard, not a timing check
    assert [r.ending.kind for r in reports] == ["interrupted", "interrupted"]
    assert all(r.ending.describe().startswith("interrupted after ") for r in reports)
    assert all(r.frames_rendered > 0 for r in reports)
    report = swarm_report(reports)
    assert report["ending"]["exit_code"] == 0
    assert report["ending"]["lines"][0].startswith("session ended early: interrupted after")
    assert report["methods"]["soa"]["hands"]["tip_p95_mm"] >= 0


# -- SIGINT to the real executable ---------------------------------------------------

_EXE = Path(sys.executable).with_name("posecast")
_COMMAND = [str(_EXE)] if _EXE.exists() else [sys.executable, "-m", "posecast.cli"]


def _start(*args: str, cwd: Path) -> subprocess.Popen[str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("POSECAST_")}
    return subprocess.Popen(
        [*_COMMAND, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=cwd,
        env=env,
    )


def _read_until(proc: subprocess.Popen[str], needle: str, limit: float = 120.0) -> str:
    """Stdout lines up to and including the first holding ``needle`` (``limit``: hang guard)."""
    assert proc.stdout is not None
    seen = ""
    with selectors.DefaultSelector() as sel:
        sel.register(proc.stdout, selectors.EVENT_READ)
        while needle not in seen:
            assert sel.select(timeout=limit), f"no {needle!r} in {seen!r}"
            line = proc.stdout.readline()
            assert line, f"exited ({proc.wait()}) before {needle!r}: {seen!r}"
            seen += line
    return seen


def _interrupt(proc: subprocess.Popen[str]) -> tuple[int, str, str]:
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)  # a hang guard, not a timing check
    return proc.returncode, out, err


def test_ctrl_c_in_demo_prints_the_report_of_the_time_run(tmp_path: Path) -> None:
    """SIGINT mid-session: the QoE table, 'interrupted after', the verdict; exit 130."""
    proc = _start("demo", "--bots", "2", "--duration", "600", "--motion", "synthetic",
                  "--no-record", cwd=tmp_path)  # fmt: skip
    try:
        before = ""
        while _relayed_in(before) < 300:  # plain progress lines: the session runs
            before = _read_until(proc, "poses relayed")
        code, out, err = _interrupt(proc)
    finally:
        proc.kill()
    assert "Traceback" not in err, err
    assert code == 130, (code, err)
    assert "session: " in before
    assert "interrupted after" in out and "the report covers that time" in out, out
    rows = [line.split() for line in out.splitlines()]
    assert any(r[:2] == ["soa", "hands"] for r in rows if len(r) > 2), out
    assert "verdict: at 15 Hz on this motion (synthetic motion" in out, out
    assert "interrupted: ending the run" in out


def test_ctrl_c_in_bots_prints_the_report_of_the_time_run(tmp_path: Path) -> None:
    """SIGINT once the bots are in the room: their table and 'interrupted after'; exit 130."""
    serve = _start("serve", "--port", "0", cwd=tmp_path)
    try:
        url = _read_until(serve, "listening on").split()[3]
        bots = _start("bots", "--url", url, "--n", "2", "--duration", "600",
                      "--motion", "synthetic", cwd=tmp_path)  # fmt: skip
        try:
            metrics = f"http://{url.removeprefix('ws://')}/metrics"
            _poll(lambda: 'posecast_room_members{room="lobby"} 2' in _get(metrics))
            _poll(lambda: _relayed(_get(metrics)) > 200)
            code, out, err = _interrupt(bots)
        finally:
            bots.kill()
    finally:
        serve.send_signal(signal.SIGINT)
        serve.communicate(timeout=60)
    assert "Traceback" not in err, err
    assert code == 130, (code, err)
    assert "session ended early: interrupted after" in out, out
    rows = [line.split() for line in out.splitlines()]
    assert any(r[:2] == ["motor-lerp", "hands"] for r in rows if len(r) > 2), out


def _relayed_in(progress: str) -> int:
    """The poses relayed of the last progress line ("session: 6/600 s, 2 bots, N poses ...")."""
    found = re.findall(r"(\d+) poses relayed", progress)
    return int(found[-1]) if found else 0


def _get(url: str) -> str:
    with urllib.request.urlopen(url, timeout=30) as resp:
        return str(resp.read().decode())


def _relayed(metrics: str) -> float:
    """Poses the relay has sent in snapshots, over its rooms."""
    return sum(
        float(line.rsplit(" ", 1)[1])
        for line in metrics.splitlines()
        if line.startswith("posecast_room_poses_out_total{")
    )


def _poll(condition: Callable[[], bool], limit: float = 120.0) -> None:
    """Poll every 0.2 s until ``condition`` holds; ``limit`` is a hang guard."""
    wait_until(condition, limit=limit, every=0.2)


def test_ctrl_c_in_table1_prints_what_was_measured(tmp_path: Path) -> None:
    """SIGINT mid offline sweep: the finished rates' errors (or Table 1 itself), which
    stage it reached, that nothing was written; exit 130."""
    proc = _start("table1", "--traces", "traces:sample", "--out", "t1", cwd=tmp_path)
    try:
        seen = ""  # plain progress lines ("ideal: 41/464"): past 20 steps, a rate is pooled
        while not re.search(r"ideal: (\d{3,}|[2-9]\d)/", seen):
            seen = _read_until(proc, "ideal: ")
        code, out, err = _interrupt(proc)
    finally:
        proc.kill()
    assert "Traceback" not in err, err
    assert code == 130, (code, err)
    assert "interrupted during the offline sweep (in " in err, err
    assert "nothing was written" in err and "--rates 5,10,15,20,30" in err
    assert "rates finished" in out or "Table 1: equal-QoE rate" in out, out
    assert not (tmp_path / "t1").exists()
