"""A bot whose path goes silent (socket open, every byte dropped) notices it by its
own keepalive and resumes, on a real relay behind a real TCP proxy on loopback.

Before, the bot kept the websockets library's 20 s + 20 s keepalive: it never
noticed a dead path within the relay's 10 s resume window, rendered mostly stalls
and reported "complete". How soon it noticed is printed, not asserted.
"""

from __future__ import annotations

import asyncio
import contextlib

from support import poll_until, running_server

from posecast.client.bot import Bot, BotConfig, BotReport


class Proxy:
    """A TCP proxy to ``port``; :meth:`blackhole` makes its open connections drop every
    byte both ways (sockets stay open), while new connections pass."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.dead: list[list[bool]] = []
        self.server: asyncio.Server | None = None

    async def start(self) -> int:
        self.server = await asyncio.start_server(self._serve, "127.0.0.1", 0)
        return int(self.server.sockets[0].getsockname()[1])

    def blackhole(self) -> None:
        for flag in self.dead:
            flag[0] = True

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        up_r, up_w = await asyncio.open_connection("127.0.0.1", self.port)
        dead = [False]
        self.dead.append(dead)

        async def pipe(src: asyncio.StreamReader, dst: asyncio.StreamWriter) -> None:
            with contextlib.suppress(ConnectionError):
                while data := await src.read(65536):
                    if not dead[0]:
                        dst.write(data)
                        await dst.drain()
            dst.close()

        try:
            async with asyncio.TaskGroup() as tg:
                tg.create_task(pipe(reader, up_w))
                tg.create_task(pipe(up_r, writer))
        except* ConnectionError:
            pass
        finally:
            for w in (writer, up_w):
                w.close()
                with contextlib.suppress(ConnectionError):
                    await w.wait_closed()

    async def close(self) -> None:
        if self.server is not None:
            self.server.close()


async def _session() -> tuple[Bot, BotReport, float]:
    async with running_server() as srv:
        proxy = Proxy(srv.port)
        port = await proxy.start()
        cfg = BotConfig(
            url=f"ws://127.0.0.1:{port}", room="b", rate=20, duration=14.0, methods=("soa",)
        )
        peer_cfg = BotConfig(
            url=f"ws://127.0.0.1:{srv.port}", room="b", rate=20, duration=14.0, methods=("soa",)
        )
        bot, peer = Bot(cfg, srv.clock), Bot(peer_cfg, srv.clock)
        async with asyncio.TaskGroup() as tg:
            task = tg.create_task(bot.run())
            tg.create_task(peer.run())
            await poll_until(lambda: any(rs.capture for rs in bot.remote.values()), limit=30.0)
            proxy.blackhole()
            cut = srv.clock()
        await proxy.close()
        return bot, task.result(), cut


def test_a_blackholed_bot_notices_by_keepalive_and_resumes() -> None:
    """The bot drops its silent connection and resumes (same user) within its window;
    the time it had no fresh poses is counted, and it does not end 'complete' unless
    most of its session was fed."""
    bot, report, cut = asyncio.run(_session())
    assert report.resumed == 1, report.ending
    assert bot.resumed_at, "it never resumed"
    print(f"\nresumed {bot.resumed_at[0] - cut:.1f} s after the path went silent")
    assert report.stale_s > 0.0
    assert report.ending.kind in ("complete", "stalled")
    assert report.ending.stale_s == report.stale_s
