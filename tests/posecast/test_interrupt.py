"""Ctrl-C ends a run early and its report covers the time run.

In process: ``run_bots(stop=...)`` ends every bot's session when the event is set;
with the real executable: SIGINT to ``posecast demo`` and ``posecast bots`` prints
the report of the time run, says it was interrupted, and exits 130.
"""

from __future__ import annotations

import asyncio

from support import poll_until, running_server

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
