"""Test support shared by every test package: a real relay on loopback."""

from __future__ import annotations

import asyncio
import inspect
import os
import shutil
import time
from collections.abc import Awaitable, Callable
from contextlib import AbstractAsyncContextManager

from posecast.server.app import RelayServer, ServerConfig, serving

__all__ = [
    "CHROMIUM_ARGS",
    "Pacer",
    "find_chromium",
    "import_root",
    "poll_until",
    "relayed",
    "running_server",
    "wait_until",
]

#: Software WebGL (SwiftShader): what a machine without a GPU (CI, this one) renders with.
CHROMIUM_ARGS = ["--use-gl=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox"]


def find_chromium() -> str | None:
    """``POSECAST_CHROMIUM``, else ``chromium`` or ``chromium-browser`` on PATH."""
    env = os.environ.get("POSECAST_CHROMIUM")
    if env:
        return env if os.path.exists(env) else None
    for name in ("chromium", "chromium-browser"):
        found = shutil.which(name)
        if found:
            return found
    return None


#: The repository's folders, each installed as ``posecast.<folder>``.
FOLDERS = frozenset({"server", "client", "protocol", "interp", "recorder", "scenarios"})


def import_root(name: str) -> str:
    """The package a module name belongs to: ``posecast.protocol.wire`` is ``protocol``
    (a folder installed under ``posecast.``), ``posecast.cli`` is ``posecast``,
    ``numpy.linalg`` is ``numpy``."""
    head, _, rest = name.partition(".")
    sub = rest.split(".")[0]
    return sub if head == "posecast" and sub in FOLDERS else head


def running_server(config: ServerConfig | None = None) -> AbstractAsyncContextManager[RelayServer]:
    """Run a RelayServer on 127.0.0.1:0 while the block runs; stop it on exit."""
    return serving(RelayServer(config or ServerConfig(host="127.0.0.1", port=0)))


# The suite's real sleeps live here (tests/test_guards.py counts them): polling an
# observable condition, and pacing a source that publishes at a rate. A test that
# needs "later" waits for what it is waiting for, through these.


async def poll_until(
    condition: Callable[[], bool | Awaitable[bool]], limit: float = 60.0, every: float = 0.02
) -> None:
    """Poll ``condition`` (plain or async) every ``every`` s until it holds; ``limit`` is
    a hang guard (TimeoutError), not a timing check."""
    async with asyncio.timeout(limit):
        while True:
            got = condition()
            if inspect.isawaitable(got):
                got = await got
            if got:
                return
            await asyncio.sleep(every)


def wait_until(condition: Callable[[], bool], limit: float = 60.0, every: float = 0.02) -> None:
    """:func:`poll_until` for code without an event loop (threads, child processes):
    ``limit`` is a hang guard (TimeoutError), not a timing check."""
    deadline = time.monotonic() + limit
    while not condition():
        if time.monotonic() > deadline:
            raise TimeoutError(f"condition not met within {limit} s (a hang guard)")
        time.sleep(every)


class Pacer:
    """Steps on a grid of ``period`` s of ``clock``, for a source publishing at 1/period Hz:
    ``await pacer.next()`` returns when the next step is due. A late step goes at once;
    the grid does not move."""

    def __init__(self, period: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.period = period
        self.clock = clock
        self.start = clock()
        self.step = 0

    async def next(self) -> int:
        """Wait for the next step of the grid; its number (1, 2, ...)."""
        self.step += 1
        await asyncio.sleep(max(0.0, self.start + self.step * self.period - self.clock()))
        return self.step


def relayed(server: RelayServer, room: str) -> int:
    """Poses the relay has sent out in ``room`` so far (0 before the room exists)."""
    r = server.rooms.get(room)
    return 0 if r is None else r.statistics().poses_out
