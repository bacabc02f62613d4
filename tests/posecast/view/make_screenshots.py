"""Write docs/viewer-live.png, docs/viewer-replay.png and docs/viewer-drill.png.

    .venv/bin/python tests/posecast/view/make_screenshots.py [--out docs] [--only drill]

Live: a relay and 5 bots playing the bundled traces (``traces:sample``) on
loopback, standing on the default spawn circle (as ``posecast bots`` does),
watched by ``LiveView`` with the camera framing the room, soa solid with
dq-slerp and motor-hermite ghosts. Replay: a recording of 4 users on a spawn
circle synthesised from the same traces through the recorder, ``ReplayView``
with ghosts from 5 Hz keyframes and hand trails (truth vs soa), at a fast
moment (the largest tip error of soa). Drill: the live throw-catch scene (3
bots, ``--motion throw-catch``) at 10 Hz, paused with the drill half-way
through its flight. Each shot waits for the 3D canvas to be drawn
(``pagekit.scene_ready``). Needs chromium; ``tests/posecast/view/test_screenshots.py``
checks the PNGs show users.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from playwright.async_api import Browser, Page, async_playwright

_HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(_HERE.parents[2]), str(_HERE.parents[1]), str(_HERE)]

from pagekit import scene_ready, until  # noqa: E402
from support import (  # noqa: E402
    CHROMIUM_ARGS,
    find_chromium,
    running_server,
)

from posecast.client.bot import BotConfig, motion_for_bot, run_bot  # noqa: E402
from posecast.client.swarm import run_bots  # noqa: E402
from posecast.recorder.replay import synthesize_recording  # noqa: E402
from posecast.scenarios.throw_catch import PERIOD, scene_script  # noqa: E402
from posecast.view.live import LiveConfig, LiveView  # noqa: E402
from posecast.view.replay import ReplayView  # noqa: E402

METHODS = ("soa", "dq-slerp", "motor-hermite")
#: Poses pushed to the page a second: few, so that a page drawn in software keeps up.
FPS = 15.0
HIDE_TOASTS = (
    ".mantine-Notifications-root, .mantine-Notification-root { display: none !important; }"
)


async def _open(browser: Browser, url: str) -> Page:
    page = await browser.new_page(viewport={"width": 1280, "height": 760})
    await page.goto(url)
    await page.add_style_tag(content=HIDE_TOASTS)
    await scene_ready(page)
    return page


def _bots(tg: asyncio.TaskGroup, url: str, room: str, spec: str, n: int) -> list[Any]:
    """Start ``n`` bots of motion ``spec`` at 10 Hz in ``room``; their tasks."""
    tasks = []
    for i in range(n):
        motion, seed = motion_for_bot(spec, i)
        cfg = BotConfig(
            url=url, room=room, rate=10.0, motion=motion, seed=seed,
            duration=400.0, methods=METHODS, name=f"bot{i}",
        )  # fmt: skip
        tasks.append(tg.create_task(run_bot(cfg)))
    return tasks


async def live_shot(browser: Browser, out: Path) -> None:
    async with running_server() as srv:
        url = f"ws://127.0.0.1:{srv.port}"
        view = LiveView(
            LiveConfig(url=url, room="demo", methods=METHODS, port=0, rate=10.0, fps=FPS)
        )
        base = BotConfig(
            url=url, room="demo", rate=10.0, motion="traces:sample", duration=400.0,
            methods=METHODS, name="bot",
        )  # fmt: skip
        try:
            async with asyncio.TaskGroup() as tg:
                tasks = [tg.create_task(view.run())]
                page = await _open(browser, view.url)
                tasks.append(tg.create_task(run_bots(base, 5, spawn="circle")))
                await until(lambda: len(view.scene.avatars) == 5 and view.frames > 60, 120)
                await asyncio.sleep(3.0)
                # Freeze the frame, then let a slow (software WebGL) page catch up with it.
                view.paused = True
                await page.wait_for_selector("text=keyframes/s", timeout=180_000)
                await asyncio.sleep(3.0)
                await page.screenshot(path=str(out))
                await page.close()
                for t in tasks:
                    t.cancel()
        finally:
            view.close()


async def drill_shot(browser: Browser, out: Path) -> None:
    script = scene_script(0)
    middle = (script.release + script.catch) / 2
    async with running_server() as srv:
        url = f"ws://127.0.0.1:{srv.port}"
        view = LiveView(
            LiveConfig(url=url, room="drill", methods=METHODS, port=0, rate=10.0, fps=FPS)
        )
        try:
            async with asyncio.TaskGroup() as tg:
                tasks = [tg.create_task(view.run())]
                page = await _open(browser, view.url)
                tasks += _bots(tg, url, "drill", "throw-catch", 3)
                await until(lambda: len(view.scene.avatars) >= 3 and view.frames > 60, 60)
                await asyncio.sleep(PERIOD)
                # Pause the page on a frame whose playout time is mid-flight, then let a
                # slow (software WebGL) page catch up with it.
                await until(lambda: abs(view.last_frame[0] % PERIOD - middle) < 0.06, 60)
                view.paused = True
                await page.wait_for_selector("text=keyframes/s", timeout=180_000)
                await asyncio.sleep(3.0)
                await page.screenshot(path=str(out))
                await page.close()
                for t in tasks:
                    t.cancel()
        finally:
            view.close()


async def replay_shot(browser: Browser, out: Path) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        rec = synthesize_recording(
            tmp, users=4, rate=30.0, duration=20.0, velocities=True, spawn="circle"
        )
        view = ReplayView(rec, METHODS, port=0, rate=5.0)
        try:
            # A fast moment: where soa's tip error at 5 Hz peaks.
            x, err = view.model.error_strip("soa")
            view.seek(view.model.start + float(x[int(np.nanargmax(err))]))
            page = await _open(browser, view.url)
            await asyncio.sleep(4.0)
            await page.screenshot(path=str(out))
            await page.close()
        finally:
            view.close()


async def main(out_dir: Path, only: str | None = None) -> None:
    chromium = find_chromium()
    if chromium is None:
        raise SystemExit("chromium not found; apt-get install chromium")
    async with async_playwright() as p:
        browser = await p.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS)
        shots = {"live": live_shot, "replay": replay_shot, "drill": drill_shot}
        for name, shot in shots.items():
            if only in (None, name):
                await shot(browser, out_dir / f"viewer-{name}.png")
                print(f"wrote {out_dir / f'viewer-{name}.png'}")
        await browser.close()


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("docs"), help="Folder for the PNGs.")
    ap.add_argument("--only", choices=("live", "replay", "drill"), help="Write just this one.")
    args = ap.parse_args()
    asyncio.run(main(args.out, args.only))
