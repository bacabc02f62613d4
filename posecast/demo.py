"""``posecast demo``: a relay and N bots in one process on loopback.

The server runs on an ephemeral port; the bots join one room, publish their
motions and render everyone else's with every interpolator; a progress bar (plain
lines when piped) shows the session; the result is the swarm report of
:mod:`client.swarm`. With ``--nodes N`` the relay is a local cluster instead
(``posecast.cluster_local``). Setting ``stop`` (Ctrl-C) ends the session early:
the report covers the time run.
"""

from __future__ import annotations

import asyncio
import logging
import statistics
import tempfile
import time
from contextlib import AsyncExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

from posecast.client.bot import BotConfig
from posecast.client.swarm import run_bots, swarm_report
from posecast.cluster_local import LocalCluster, local_cluster
from posecast.progress import PlainProgress, progress
from posecast.server.app import RelayServer, ServerConfig, serving
from posecast.server.link import LinkTier

__all__ = ["RateLog", "run_demo"]


async def run_demo(
    *,
    bots: int,
    rate: float,
    duration: float,
    auto_rate: bool = False,
    methods: tuple[str, ...],
    motion: str,
    send_rate: float = 30.0,
    console: Console | None = None,
    record_dir: Path | None = None,
    codec: str = "compact",
    view_port: int | None = None,
    nodes: int = 1,
    kill: tuple[str, float] | None = None,
    spawn: str = "none",
    stop: asyncio.Event | None = None,
    link: LinkTier | None = None,
    budget_deg: float | None = None,
) -> dict[str, Any]:
    """Run the demo; with ``view_port``, a live viewer of its room is served there too.

    With ``auto_rate`` the bots join with rate "auto" (up to ``rate``) and the demo
    asks the relay what it sends each (:class:`RateLog`): the report gains ``rates``;
    ``budget_deg``: the bots join with that error budget, and ``rates`` has each
    peer's rate to each bot too.
    ``link`` emulates that tier on every bot's downlink (``serve --link``; one relay).

    With ``nodes`` > 1 the relay is a cluster on this machine: a nats-server and
    that many ``posecast serve --cluster`` processes, the bots spread over them
    (bot i on node i % nodes); the report gains ``cluster``: each node, its bots,
    the room's owner, and the age of the snapshots the bots got on the owner and
    through another node (the cross-node path's cost). ``kill`` (node name or
    ``owner``, seconds after the bots start) SIGKILLs that node then: the
    node-loss drill; ``cluster.kill`` reports each bot's longest snapshot gap and
    what the recordings hold (the killed node's file recovered)."""
    async with AsyncExitStack() as stack:
        cluster, server, urls = await _relays(stack, nodes, record_dir, link)
        tg = await stack.enter_async_context(asyncio.TaskGroup())
        viewer = (
            None if view_port is None else _start_view(tg, urls[0], methods, view_port, console)
        )
        base = BotConfig(url=urls[0], urls=tuple(urls), room="demo", rate=rate,
                         send_rate=send_rate, methods=methods, motion=motion,
                         duration=duration, name="bot", codec=codec,
                         auto_rate=auto_rate, budget_deg=budget_deg)  # fmt: skip
        seen: dict[str, dict[str, float]] = {}
        rates = RateLog() if auto_rate or budget_deg is not None else None
        killed: dict[str, Any] = {}
        with _progress(console) as bar:
            helpers = [tg.create_task(_watch(bar, duration, server, cluster, seen, rates))]
            if rates is not None:
                helpers.append(tg.create_task(rates.watch(urls, "demo")))
            if kill is not None and cluster is not None:
                helpers.append(tg.create_task(_kill_later(cluster, seen, kill, killed, console)))
            try:
                reports = await run_bots(base, bots, spawn=spawn, stop=stop)
            finally:
                for task in [*helpers, *([viewer] if viewer is not None else [])]:
                    task.cancel()
        report = swarm_report(reports)
        report |= {"rates": rates.report(report["bots"])} if rates is not None else {}
        report["server"] = {"url": ",".join(urls), "rate_hz": rate, "auto_rate": auto_rate,
                            "send_rate_hz": send_rate, "link": getattr(link, "name", None),
                            "budget_deg": budget_deg,
                            "duration_s": duration, "motion": motion, "codec": codec}  # fmt: skip
        if cluster is not None:
            report["cluster"] = _cluster_report(cluster, report["bots"], seen)
            if killed:
                report["cluster"]["kill"] = killed
        if server is not None:
            server.stop()
    if killed and record_dir is not None:
        killed["recordings"] = await asyncio.to_thread(_drill_files, record_dir, killed)
    if server is not None:
        report["recording"] = str(server.recordings[-1]) if server.recordings else None
    else:
        report["recording"] = await asyncio.to_thread(_newest_recording, record_dir)
    return report


async def _relays(
    stack: AsyncExitStack, nodes: int, record_dir: Path | None, link: LinkTier | None
) -> tuple[LocalCluster | None, RelayServer | None, list[str]]:
    """The demo's relay (or local cluster of ``nodes``), run until ``stack`` closes:
    (cluster, server, their URLs)."""
    if nodes > 1:
        store = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="posecast-")))
        cluster = await stack.enter_async_context(local_cluster(nodes, store, record_dir))
        return cluster, None, list(cluster.urls)
    server = await stack.enter_async_context(serving(_local_relay(record_dir, link)))
    return None, server, [f"ws://127.0.0.1:{server.port}"]


def _newest_recording(record_dir: Path | None) -> str | None:
    """The cluster's recording of the demo: the latest started, of any node's folder."""
    files = [] if record_dir is None else list(record_dir.glob("node*/*.mcap"))
    return str(max(files, key=lambda p: p.name)) if files else None  # NAME-<start time>


def _local_relay(record_dir: Path | None, link: LinkTier | None = None) -> RelayServer:
    """The demo's relay: open (no secret, on loopback: no warning about it), no
    keepalive pings (bots and relay share one loop, which a busy machine makes
    answer late), time to load the motions before joining (longer than a
    public relay's 5 s join timeout), no capacity budget (its CPU reading is
    the whole process's, bots included: it would turn the demo's own bots away),
    and ``link`` emulated on every downlink (None: loopback as it is)."""
    _quiet_open_relay()
    return RelayServer(
        ServerConfig(host="127.0.0.1", port=0, record_dir=record_dir,
                     join_timeout=60.0, ping_interval=0.0,
                     capacity_cpu=0.0, capacity_lag=0.0, link=link)
    )  # fmt: skip


def _quiet_open_relay() -> None:
    """The demo's relay is on loopback with no secret on purpose: no warning about it."""
    logger = logging.getLogger("posecast.server")
    if not any(isinstance(f, _NoOpenWarning) for f in logger.filters):
        logger.addFilter(_NoOpenWarning())


class _NoOpenWarning(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return "no --secret" not in str(record.msg)


@dataclass
class RateLog:
    """The snapshot rate the relay sends each member of a room, as its ``GET /rates``
    answers (``posecast.view.rates``), asked every ``period`` s while the demo runs:
    the relay's own choice (an auto rate's), not a rate measured at the bots."""

    period: float = 0.5
    #: User id -> the rates answered for it, in order.
    samples: dict[int, list[float]] = field(default_factory=dict)
    #: The last answer: user id -> rate (Hz).
    current: dict[int, float] = field(default_factory=dict)
    #: (subscriber, peer) -> the rates of that peer's streams to that subscriber, for
    #: members with an error budget (``join.budget_deg``).
    peer_samples: dict[tuple[int, int], list[float]] = field(default_factory=dict)
    answers: int = 0
    failures: int = 0

    def add(
        self, rates: dict[int, float], peers: dict[int, dict[int, float]] | None = None
    ) -> None:
        """One answer of the relay (user id -> Hz; ``peers``: subscriber -> peer -> Hz)."""
        self.answers += 1
        self.current = dict(rates)
        for user, rate in rates.items():
            self.samples.setdefault(user, []).append(rate)
        for user, by_peer in (peers or {}).items():
            for peer, rate in by_peer.items():
                self.peer_samples.setdefault((user, peer), []).append(rate)

    async def watch(self, urls: list[str], room: str) -> None:
        """Ask every relay of ``urls`` for ``room``'s rates every ``period`` s, until
        cancelled; an unanswered question is counted in ``failures``."""
        from posecast.view.rates import fetch_rate_table

        while True:
            merged: dict[str, dict[str, Any]] = {}
            answered = False
            for url in urls:
                try:
                    merged.update(await fetch_rate_table(url, room))
                    answered = True
                except (OSError, TimeoutError, ValueError, KeyError):
                    self.failures += 1
            if answered:
                rates = {int(u): float(v["rate"]) for u, v in merged.items()}
                peers = {
                    int(u): {int(p): float(r) for p, r in v["peers"].items()}
                    for u, v in merged.items()
                    if "peers" in v
                }
                self.add(rates, peers)
            await asyncio.sleep(self.period)

    def line(self) -> str:
        """The rates now, for the session line: each member's (by user id) up to 8,
        else their range and median."""
        rates = [self.current[u] for u in sorted(self.current)]
        if len(rates) <= 8:
            return "relay rates " + " ".join(f"{r:g}" for r in rates) + " Hz"
        mid = statistics.median(rates)
        return f"relay rates {min(rates):g}-{max(rates):g} Hz (median {mid:g})"

    def report(self, bots: list[dict[str, Any]]) -> dict[str, Any]:
        """The ``rates`` key of the demo's report; each of ``bots`` (swarm report rows)
        gains ``relay_rate_hz`` (the last answer that listed it) and ``relay_mean_hz``
        (the mean of the answers; NaN when no answer listed it), and with an error
        budget ``relay_peer_mean_hz`` (peer id -> the mean of its rates to the bot)."""
        nan = float("nan")
        users: dict[str, dict[str, Any]] = {
            str(u): {"now_hz": r[-1], "mean_hz": statistics.fmean(r), "min_hz": min(r),
                     "max_hz": max(r), "answers": len(r)}
            for u, r in sorted(self.samples.items())
        }  # fmt: skip
        for (user, peer), r in sorted(self.peer_samples.items()):
            if str(user) in users:
                users[str(user)].setdefault("peers_mean_hz", {})[str(peer)] = statistics.fmean(r)
        for b in bots:
            got = users.get(str(b["id"]), {})
            b["relay_rate_hz"] = got.get("now_hz", nan)
            b["relay_mean_hz"] = got.get("mean_hz", nan)
            if "peers_mean_hz" in got:
                b["relay_peer_mean_hz"] = got["peers_mean_hz"]
        every = [x for r in self.samples.values() for x in r]
        return {
            "source": f"GET /rates?room=demo every {self.period:g} s",
            "answers": self.answers,
            "failures": self.failures,
            "mean_hz": statistics.fmean(every) if every else nan,
            "users": users,
        }


def _progress(console: Console | None) -> Progress | PlainProgress:
    columns = (
        TextColumn("[bold]session[/]"),
        BarColumn(),
        TextColumn("{task.description}"),
        TimeRemainingColumn(),
    )
    if console is None:
        return Progress(*columns, transient=True)
    return progress(console, *columns, unit="s", name="session")


async def _watch(
    bar: Progress | PlainProgress,
    duration: float,
    server: RelayServer | None,
    cluster: LocalCluster | None,
    seen: dict[str, dict[str, float]],
    rates: RateLog | None = None,
) -> None:
    """The progress bar; a cluster's figures (rooms owned, members forwarded) into
    ``seen`` by node, as last read during the session; ``rates``: the rates the relay
    sends each bot now, after the figures."""
    task = bar.add_task("", total=duration)
    loop = asyncio.get_running_loop()
    start = loop.time()
    while True:
        await asyncio.sleep(0.5)
        if server is not None:
            stats = server.statistics()
            rooms = stats["rooms"]
            assert isinstance(rooms, dict)
            room = rooms.get("demo")
            desc = (
                f"{stats['connections']} bots, {room.poses_out} poses relayed, {room.skips} skips"
                if room is not None
                else "starting"
            )
        else:
            assert cluster is not None
            for relay in cluster.relays:
                # The largest value of each figure during the session (the members
                # are gone by the end).
                kept = seen.setdefault(relay.name, {})
                for key, value in (await relay.metrics()).items():
                    kept[key] = max(value, kept.get(key, value))
            owner = [n for n, f in seen.items() if f.get("posecast_cluster_rooms_owned", 0) > 0]
            forwarded = sum(f.get("posecast_cluster_remote_members", 0) for f in seen.values())
            desc = (
                f"{len(cluster.relays)} nodes, room on {', '.join(owner) or '?'}, "
                f"{forwarded:g} bots through other nodes"
            )
        if rates is not None and rates.current:
            desc += f"; {rates.line()}"
        bar.update(task, completed=min(duration, loop.time() - start), description=desc)


async def _kill_later(
    cluster: LocalCluster,
    seen: dict[str, dict[str, float]],
    kill: tuple[str, float],
    out: dict[str, Any],
    console: Console | None,
) -> None:
    """The drill: SIGKILL node ``kill[0]`` (``owner``: the room's) ``kill[1]`` s in."""
    name, at = kill
    await asyncio.sleep(at)
    if name == "owner":
        owners = [n for n, f in seen.items() if f.get("posecast_cluster_rooms_owned", 0) > 0]
        name = owners[0] if owners else cluster.relays[0].name
    relay = next(r for r in cluster.relays if r.name == name)
    relay.kill()
    out.update({"node": name, "at_s": at, "wall_time": time.time()})
    if console is not None:
        console.print(f"drill: node {name} SIGKILLed {at:g} s into the session")


def _drill_files(record_dir: Path, killed: dict[str, Any]) -> list[dict[str, Any]]:
    """Each node's recordings after the drill; the killed node's unfinished file is
    recovered first (as that node would at its next start)."""
    from posecast.recorder import find_leftovers, info, recover

    for part in find_leftovers(record_dir / killed["node"]):
        recover(part)
    out = []
    for path in sorted(record_dir.glob("node*/*.mcap")):
        summary = info(path)
        last = summary["last_time"]
        out.append(
            {
                "path": str(path),
                "node": summary.get("cluster_node"),
                "continues_from_node": summary.get("continues_from_node"),
                "users": len(summary["users"]),
                "poses": summary["sizes"]["poses"],
                # Server clock = wall clock on a cluster node: how long before the
                # kill the killed node's file ends (its unwritten tail).
                "ends_before_kill_s": None if last is None else killed["wall_time"] - last,
            }
        )
    return out


def _cluster_report(
    cluster: LocalCluster, bots: list[dict[str, Any]], seen: dict[str, dict[str, float]]
) -> dict[str, Any]:
    """Nodes, the bots on each, the room's owner, and the snapshot age on the owner and
    through another node."""
    nan = float("nan")
    owners = [n for n, f in seen.items() if f.get("posecast_cluster_rooms_owned", 0) > 0]
    owner = owners[0] if len(owners) == 1 else None
    for b in bots:
        b["node"] = cluster.node_of(b.get("relay"))

    def age(group: list[dict[str, Any]], key: str) -> float:
        values = [b[key] for b in group if b[key] == b[key]]
        return float(statistics.median(values)) if values else nan

    on_owner = [b for b in bots if owner is not None and b["node"] == owner]
    through = [b for b in bots if owner is not None and b["node"] not in (owner, None)]
    return {
        "nats": cluster.nats.url,
        "owner": owner,
        "nodes": [
            {
                "name": r.name,
                "url": r.url,
                "bots": sum(b["node"] == r.name for b in bots),
                "rooms_owned": seen.get(r.name, {}).get("posecast_cluster_rooms_owned", nan),
                "remote_members": seen.get(r.name, {}).get("posecast_cluster_remote_members", nan),
                "nats_rtt_ms": 1e3
                * seen.get(r.name, {}).get("posecast_cluster_nats_rtt_seconds", float("nan")),
            }
            for r in cluster.relays
        ],
        # Snapshot age (the owner's send time -> receipt), median over the bots of
        # each group: the cross-node path adds edge -> client via NATS.
        "snapshot_age_ms_on_owner": {
            "p50": age(on_owner, "snapshot_age_ms_p50"),
            "p99": age(on_owner, "snapshot_age_ms_p99"),
        },
        "snapshot_age_ms_through_other_node": {
            "p50": age(through, "snapshot_age_ms_p50"),
            "p99": age(through, "snapshot_age_ms_p99"),
        },
    }


def _start_view(
    tg: asyncio.TaskGroup, url: str, methods: tuple[str, ...], port: int, console: Console | None
) -> asyncio.Task[None]:
    """``demo --view``: a spectator of the demo's room, served on ``port``."""
    from posecast.view.live import LiveConfig, run_live_view

    cfg = LiveConfig(url=url, room="demo", methods=methods, port=port)

    def ready(view: Any) -> None:
        if console is not None:
            console.print(f"viewer at [bold]{view.url}[/] (open it in a browser)")

    return tg.create_task(run_live_view(cfg, ready))
