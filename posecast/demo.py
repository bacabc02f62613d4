"""``posecast demo``: a relay and N bots in one process on loopback.

The server runs on an ephemeral port; the bots join one room, publish their
motions and render everyone else's with every interpolator; a rich progress bar
shows the session; the result is the swarm report of :mod:`client.swarm`.
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

from client.bot import BotConfig
from client.swarm import run_bots, swarm_report
from server.app import RelayServer, ServerConfig

__all__ = ["run_demo"]


async def run_demo(
    *,
    bots: int,
    rate: float,
    duration: float,
    methods: tuple[str, ...],
    motion: str,
    send_rate: float = 30.0,
    console: Console | None = None,
    record_dir: Path | None = None,
    codec: str = "compact",
) -> dict[str, Any]:
    server = RelayServer(ServerConfig(host="127.0.0.1", port=0, record_dir=record_dir))
    async with asyncio.TaskGroup() as tg:
        tg.create_task(server.run())
        await asyncio.wait_for(server.ready.wait(), 10)
        url = f"ws://127.0.0.1:{server.port}"
        base = BotConfig(
            url=url,
            room="demo",
            rate=rate,
            send_rate=send_rate,
            methods=methods,
            motion=motion,
            duration=duration,
            name="bot",
            codec=codec,
        )
        progress = Progress(
            TextColumn("[bold]session[/]"),
            BarColumn(),
            TextColumn("{task.description}"),
            TimeRemainingColumn(),
            console=console,
            transient=True,
        )

        async def watch() -> None:
            task = progress.add_task("", total=duration)
            loop = asyncio.get_running_loop()
            start = loop.time()
            while True:
                await asyncio.sleep(0.5)
                stats = server.statistics()
                rooms = stats["rooms"]
                assert isinstance(rooms, dict)
                room = rooms.get("demo")
                desc = (
                    f"{stats['connections']} bots, {room.poses_out} poses relayed, "
                    f"{room.skips} skips"
                    if room is not None
                    else "starting"
                )
                progress.update(
                    task, completed=min(duration, loop.time() - start), description=desc
                )

        with progress:
            watcher = tg.create_task(watch())
            try:
                reports = await run_bots(base, bots)
            finally:
                watcher.cancel()
        report = swarm_report(reports)
        report["server"] = {
            "url": url,
            "rate_hz": rate,
            "send_rate_hz": send_rate,
            "duration_s": duration,
            "motion": motion,
            "codec": codec,
        }
        server.stop()
    report["recording"] = str(server.recordings[-1]) if server.recordings else None
    return report
