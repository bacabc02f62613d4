"""The stamp rule in a live relay: real bots (clock sync, publisher, renderer), a slow
jittered path through a delaying TCP proxy, injected clocks, and a lagging liar."""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator

import numpy as np
import pytest
from support import running_server

from posecast.client.bot import BotConfig, run_bot
from posecast.server.app import RelayServer, ServerConfig
from posecast.server.http import metrics_text

pytestmark = pytest.mark.xdist_group("live-relay")


async def _pipe(
    reader: asyncio.StreamReader, writer: asyncio.StreamWriter, delay: float, jitter: float
) -> None:
    """Copy ``reader`` to ``writer``, each chunk ``delay`` s plus a jitter later, in order."""
    rng = np.random.default_rng()
    due: asyncio.Queue[tuple[float, bytes]] = asyncio.Queue(maxsize=4096)

    async def deliver() -> None:
        last = 0.0
        while True:
            at, data = await due.get()
            if not data:
                break
            last = max(last, at)
            await asyncio.sleep(max(0.0, last - time.monotonic()))
            writer.write(data)
            await writer.drain()
        writer.close()

    task = asyncio.create_task(deliver())
    try:
        while data := await reader.read(65536):
            await due.put((time.monotonic() + delay + float(rng.gamma(2.0, jitter / 2)), data))
    except ConnectionError:
        pass
    finally:
        await due.put((0.0, b""))
        with contextlib.suppress(ConnectionError):
            await task


@contextlib.asynccontextmanager
async def slow_path(port: int, one_way: float, jitter: float) -> AsyncIterator[int]:
    """A TCP proxy to ``port`` on loopback adding ``one_way`` s (plus jitter) each way."""
    pipes: set[asyncio.Task[None]] = set()

    async def serve(r: asyncio.StreamReader, w: asyncio.StreamWriter) -> None:
        ur, uw = await asyncio.open_connection("127.0.0.1", port)
        for t in (_pipe(r, uw, one_way, jitter), _pipe(ur, w, one_way, jitter)):
            task = asyncio.create_task(t)
            pipes.add(task)
            task.add_done_callback(pipes.discard)

    proxy = await asyncio.start_server(serve, "127.0.0.1", 0)
    try:
        yield proxy.sockets[0].getsockname()[1]
    finally:
        proxy.close()
        for task in list(pipes):
            task.cancel()
        await asyncio.gather(*pipes, return_exceptions=True)


Seen = dict[int, tuple[int, float, float, float]]


async def _watch(srv: RelayServer, seen: Seen) -> None:
    """Per user, while connected: updates re-stamped, largest correction, round trip,
    largest unexplained lag judged."""
    while True:
        for peer in srv.core.peers.values():
            if peer.user is not None:
                shift = max(peer.stamps.shifts().values(), default=0.0)
                lag = max(peer.stamps.lags().values(), default=-1.0)
                was = seen.get(peer.user, (0, 0.0, 0.0, -1.0))
                seen[peer.user] = (
                    peer.stamps.corrected, max(was[1], shift), peer.stamps.rtt, max(was[3], lag)
                )  # fmt: skip
        await asyncio.sleep(0.05)


async def test_honest_bots_are_untouched_and_a_liar_is_re_stamped() -> None:
    """Three real bots for 5 s: one on a 60 ms +- jitter path each way, one on loopback
    with its clock 1000 s off (it syncs), and one stamping 60 ms late (``clock_error``).
    The relay re-stamps the liar's updates alone, by about its lag; the honest bots'
    updates are stored as they came (none moved, the metric counts the liar's)."""
    async with running_server(ServerConfig(host="127.0.0.1", port=0)) as srv:
        async with slow_path(srv.port, 0.06, 0.01) as proxied:

            def bot(name: str, port: int, **kw: object) -> BotConfig:
                return BotConfig(
                    url=f"ws://127.0.0.1:{port}", room="stamps", name=name, rate=20.0,
                    methods=("soa",), duration=5.0, **kw,
                )  # fmt: skip

            seen: Seen = {}
            watch = asyncio.create_task(_watch(srv, seen))
            try:
                far, skewed, liar = await asyncio.gather(
                    run_bot(bot("far", proxied)),
                    run_bot(bot("skewed", srv.port), clock=lambda: time.monotonic() + 1000.0),
                    run_bot(bot("liar", srv.port, clock_error=-0.06)),
                )
            finally:
                watch.cancel()
                await asyncio.gather(watch, return_exceptions=True)
        text = metrics_text(srv.core, srv.clock())
    # Both honest bots were judged (a lag under the threshold), none of their updates moved.
    assert seen[far.user][0] == 0 and seen[far.user][2] > 0.1 and -1.0 < seen[far.user][3] < 0.025
    assert seen[skewed.user][0] == 0 and -1.0 < seen[skewed.user][3] < 0.025
    moved, shift, _, _ = seen[liar.user]
    assert moved > 0 and abs(shift - 0.06) < 0.02
    assert _metric(text) >= moved


def _metric(text: str) -> int:
    for line in text.splitlines():
        if line.startswith("posecast_stamps_moved_total "):
            return int(line.split()[1])
    raise AssertionError("no posecast_stamps_moved_total")
