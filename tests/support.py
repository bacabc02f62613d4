"""Test support shared by every test package: a real relay on loopback."""

from __future__ import annotations

import asyncio
import os
import shutil
from collections.abc import Callable
from contextlib import AbstractAsyncContextManager

from posecast.server.app import RelayServer, ServerConfig, serving

__all__ = [
    "CHROMIUM_ARGS",
    "find_chromium",
    "import_root",
    "poll_until",
    "relayed",
    "running_server",
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


async def poll_until(
    condition: Callable[[], bool], limit: float = 60.0, every: float = 0.02
) -> None:
    """Poll ``condition`` every ``every`` s until it holds; ``limit`` is a hang guard
    (TimeoutError), not a timing check."""
    async with asyncio.timeout(limit):
        while True:
            if condition():
                return
            await asyncio.sleep(every)


def relayed(server: RelayServer, room: str) -> int:
    """Poses the relay has sent out in ``room`` so far (0 before the room exists)."""
    r = server.rooms.get(room)
    return 0 if r is None else r.statistics().poses_out
