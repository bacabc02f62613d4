"""Measure the live viewer with N remote users: the page's frame rate and the viewer's CPU.

    nice -n 5 .venv/bin/python tests/posecast/view/measure_view.py [--users 10] [--seconds 20]

Three processes, as a user runs them: ``posecast serve``, ``posecast bots --n N``
(real traces, ``traces:sample``) and ``posecast view --url`` (the spectator and
its page server). A headless Chromium (software WebGL, SwiftShader) opens the
page; the frame rate is counted with requestAnimationFrame over the window, and
the viewer process's CPU is its user + system time from /proc over the same
window, as a share of one core. Also prints how many users the overlay lists,
to show every user arrived. Prints figures only; decides nothing.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import re
import socket
import sys
import time
from pathlib import Path

from playwright.async_api import async_playwright

_HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(_HERE.parents[2]), str(_HERE.parents[1]), str(_HERE)]

from pagekit import FPS_JS  # noqa: E402
from support import CHROMIUM_ARGS, find_chromium  # noqa: E402

POSECAST = [sys.executable, "-m", "posecast.cli"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


async def _start(*args: str) -> asyncio.subprocess.Process:
    return await asyncio.create_subprocess_exec(
        *POSECAST, *args, stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.DEVNULL
    )


async def measure(users: int, seconds: float, fps: float) -> None:
    relay, page_port = _free_port(), _free_port()
    url = f"ws://127.0.0.1:{relay}"
    procs = [await _start("serve", "--port", str(relay))]
    try:
        await asyncio.sleep(2.0)
        bots = ["bots", "--url", url, "--n", str(users), "--room", "m"]
        bots += ["--rate", "10", "--interp", "soa", "--duration", str(seconds + 40)]
        procs.append(await _start(*bots))
        view = ["view", "--url", url, "--room", "m", "--port", str(page_port)]
        view += ["--fps", str(fps), "--spread", "1.0", "--rate", "10"]
        viewer = await _start(*view)
        procs.append(viewer)
        chromium = find_chromium()
        if chromium is None:
            raise SystemExit("chromium not found")
        async with async_playwright() as p:
            browser = await p.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS)
            page = await browser.new_page(viewport={"width": 1280, "height": 760})
            for _ in range(100):
                try:
                    await page.goto(f"http://127.0.0.1:{page_port}")
                    break
                except Exception:  # the viewer is still starting
                    await asyncio.sleep(0.3)
            await page.wait_for_selector("text=keyframes/s", timeout=60_000)
            await asyncio.sleep(5.0)  # every bot joined and is drawn
            c0, t0 = _cpu_s(viewer.pid), time.monotonic()
            rates = []
            while time.monotonic() - t0 < seconds:
                rates.append(await page.evaluate(FPS_JS))
            c1, t1 = _cpu_s(viewer.pid), time.monotonic()
            text = await page.inner_text("body")
            rows = len(set(re.findall(r"\bu(\d+)\s", text)))
            await page.screenshot(path="/tmp/posecast-measure-view.png")
            await browser.close()
        print(
            f"{users} remote users, viewer pushing {fps:g} frames/s: page "
            f"{sum(rates) / len(rates):.1f} frames/s (min {min(rates):.1f}, {len(rates)} windows "
            f"of 2 s); viewer process CPU {100 * (c1 - c0) / (t1 - t0):.0f} % of one core "
            f"over {t1 - t0:.0f} s; users in the overlay {rows}"
        )
    finally:
        for proc in reversed(procs):
            proc.terminate()
        for proc in procs:
            await asyncio.wait_for(proc.wait(), 10)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--users", type=int, default=10, help="Remote users (bots).")
    ap.add_argument("--seconds", type=float, default=20.0, help="Measurement window (s).")
    ap.add_argument("--fps", type=float, default=60.0, help="The viewer's --fps.")
    args = ap.parse_args()
    asyncio.run(measure(args.users, args.seconds, args.fps))
