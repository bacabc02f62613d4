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
    view_port: int | None = None,
) -> dict[str, Any]:
    """Run the demo; with ``view_port``, a live viewer of its room is served there too."""
    server = RelayServer(ServerConfig(host="127.0.0.1", port=0, record_dir=record_dir))
    async with asyncio.TaskGroup() as tg:
        tg.create_task(server.run())
        await asyncio.wait_for(server.ready.wait(), 10)
        url = f"ws://127.0.0.1:{server.port}"
        viewer = None if view_port is None else _start_view(tg, url, methods, view_port, console)
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
                if viewer is not None:
                    viewer.cancel()
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


def _start_view(
    tg: asyncio.TaskGroup, url: str, methods: tuple[str, ...], port: int, console: Console | None
) -> asyncio.Task[None]:
    """``demo --view``: a spectator of the demo's room, served on ``port`` (users 1 m apart)."""
    from posecast.view.live import LiveConfig, run_live_view

    cfg = LiveConfig(url=url, room="demo", methods=methods, port=port, spread=1.0)

    def ready(view: Any) -> None:
        if console is not None:
            console.print(f"viewer at [bold]{view.url}[/] (open it in a browser)")

    return tg.create_task(run_live_view(cfg, ready))
