"""``posecast demo --view``: the demo's own room, watched in the browser while it runs."""

from __future__ import annotations

import asyncio
import contextlib
import io
import re

from pagekit import until
from playwright.async_api import Page
from rich.console import Console
from support import poll_until

from posecast.demo import run_demo


async def test_demo_view_serves_the_demo_room(page: Page) -> None:
    """The demo prints the viewer's address, the page lists both bots, the demo ends as usual."""
    out = io.StringIO()
    console = Console(file=out, width=200)
    demo = asyncio.create_task(
        run_demo(
            bots=2,
            rate=15.0,
            duration=10.0,
            methods=("soa",),
            motion="traces:sample",
            console=console,
            view_port=0,
        )
    )
    await until(lambda: "viewer at http://" in out.getvalue() or demo.done(), 30)
    found = re.search(r"viewer at (http://127\.0\.0\.1:\d+)", out.getvalue())
    assert found, out.getvalue()
    await page.goto(found.group(1))
    await page.wait_for_selector("text=keyframes/s", timeout=30_000)
    users: set[str] = set()

    async def both_shown() -> bool:  # the second bot may join a moment later
        nonlocal users
        users = set(re.findall(r"\bu(\d+)\s", await page.inner_text("body")))
        return len(users) == 2

    with contextlib.suppress(TimeoutError):  # asserted below, with the report
        await poll_until(both_shown, limit=10.0, every=0.25)
    report = await asyncio.wait_for(demo, 60)
    assert page.errors == []  # type: ignore[attr-defined]
    assert len(users) == 2
    assert len(report["bots"]) == 2
    assert report["ending"]["exit_code"] == 0
