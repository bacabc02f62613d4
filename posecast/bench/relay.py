"""The relay benchmark's controller: one run, recorder rounds, interleaved rounds."""

from __future__ import annotations

import math
import os
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rich.console import Console

from posecast.bench.common import (
    _BASELINE_BOOT,
    _LISTENING,
    _SERVER_BOOT,
    DEFAULT_MOTION,
    STREAMS,
    Motion,
    _raise_nofile,
)
from posecast.bench.fleet import LoadFleet, join_figures
from posecast.bench.procs import (
    _Child,
    _children_run_time,
    _delta,
    _gauge,
    _histogram_quantile,
    _machine_cpu,
    _proc_cpu,
    _scrape,
    _sleep_until,
    _value,
)
from posecast.bench.recorder import (
    _PHASE_SETTLE,
    _disk_figures,
    _interleaved_phases,
    _interleaved_summary,
    _median_summary,
    _print_interleaved,
    _print_recorder_table,
    _recorder_summary,
)
from posecast.bench.report import print_relay_report, saturation
from posecast.protocol import codec as _codec

#: The servers ``posecast bench relay`` can run under the load.
SERVERS = ("relay", "baseline")
CODECS = ("raw", "compact")


def run_relay_bench(
    clients: int,
    room_size: int,
    rate: float,
    duration: float,
    *,
    record: bool = False,
    record_writer: str = "process",
    repeat: int = 1,
    console: Console | None = None,
    warmup: float = 5.0,
    ramp_rate: float = 50.0,
    seed: int = 0,
    interleave: float = 0.0,
    procs: int = 1,
    codec: str = "raw",
    server: str = "relay",
    motion: str = DEFAULT_MOTION,
    shed: bool = False,
) -> dict[str, Any]:
    """Run the relay benchmark; print and return its report (figures, never pass/fail).

    Like the connection and room limits, the relay's capacity budget is lifted (the
    relay admits every client it is asked to) unless ``shed``: then it runs with its
    default budget and refuses what it cannot hold (``server-full``); the report
    counts admitted, refused (by code) and hung clients either way.

    The load runs in ``procs`` processes, its clients' updates coded as
    ``codec`` (``raw`` or ``compact``) and carrying ``motion`` (``static`` or a
    trace set such as ``traces:sample``, see :class:`~posecast.bench.common.Motion`);
    ``server`` is ``relay`` (``posecast serve``) or ``baseline`` (the bare
    broadcast server of :mod:`posecast.bench.baseline`).

    ``clients`` load clients join rooms of ``room_size``, each publishes 3 streams
    at ``rate`` Hz and subscribes at ``rate``; connections ramp up at
    ``ramp_rate`` per second, measuring starts ``warmup`` s after the last join
    and lasts ``duration`` s. With ``record`` the same load runs recorder off,
    then on (with each of ``record_writer``: ``process``, ``thread`` or
    ``both``), ``repeat`` times alternating (the paper's Table 4), and the report
    adds ``{"recorder": {...}}`` with the cost ratio and bytes per pose on disk
    (medians over the rounds, each round's loss listed).

    With ``interleave`` > 0 each round is instead one recording run whose window
    is cut into phases of ``interleave`` s, recording paused and resumed in
    turn; ``{"recorder_interleaved": {...}}`` compares paired phases of the
    same server process (:func:`_interleaved_summary`).
    """
    console = console or Console()
    args = (clients, room_size, rate, duration)
    opts: dict[str, Any] = {
        "warmup": warmup,
        "ramp_rate": ramp_rate,
        "seed": seed,
        "procs": procs,
        "codec": codec,
        "server": server,
        "motion": motion,
        "shed": shed,
    }
    Motion(motion, rate if rate > 0 else 1.0)  # a bad trace set: one ValueError, here
    if procs < 1:
        raise ValueError("procs must be at least 1")
    if codec not in CODECS:
        raise ValueError(f"codec must be raw or compact, not {codec!r}")
    if server not in SERVERS:
        raise ValueError(f"server must be relay or baseline, not {server!r}")
    if record and server != "relay":
        raise ValueError("only the relay records")
    if not record:
        return _run_once(*args, record_dir=None, console=console, **opts)
    writers = ["process", "thread"] if record_writer == "both" else [record_writer]
    if any(w not in ("process", "thread") for w in writers):
        raise ValueError(f"record_writer must be process, thread or both, not {record_writer!r}")
    if repeat < 1:
        raise ValueError("repeat must be at least 1")
    if interleave < 0 or (interleave > 0 and interleave < 2 * _PHASE_SETTLE):
        raise ValueError(f"interleave must be 0 or at least {2 * _PHASE_SETTLE:g} s")
    if interleave > 0:
        return _run_interleaved(args, writers, repeat, interleave, console, opts)
    return _run_alternating(args, writers, repeat, console, opts)


def _run_alternating(
    args: tuple[int, int, float, float],
    writers: list[str],
    repeat: int,
    console: Console,
    opts: dict[str, Any],
) -> dict[str, Any]:
    """``repeat`` rounds of a recorder-off run and one run per writer (Table 4)."""
    # Off and on alternate in a balanced order (off first in even rounds, last
    # in odd ones): a drift of a shared machine, or anything that favours the
    # first or second run of a round, hits both alike. Each on-run is compared
    # with the off-run of its own round.
    pairs: dict[str, list[dict[str, Any]]] = {w: [] for w in writers}
    runs: dict[str, dict[str, Any]] = {}
    offs: list[dict[str, Any]] = []
    for k in range(repeat):
        if repeat > 1:
            console.print(f"[bold]recorder cost: round {k + 1} of {repeat}[/bold]")
        order: list[str | None] = [None, *writers]
        if k % 2:
            order.reverse()
        off: dict[str, Any] | None = None
        for writer in order:
            if writer is None:
                off = _run_once(*args, record_dir=None, console=console, **opts)
                offs.append(off)
                continue
            with tempfile.TemporaryDirectory(prefix="posecast-bench-") as tmp:
                on = _run_once(
                    *args, record_dir=Path(tmp), record_writer=writer, console=console, **opts
                )
                # Read what the summary needs while the files exist.
                disk = _disk_figures(sorted(Path(tmp).glob("*.mcap")))
                pairs[writer].append({"on": on, "disk": disk})
                runs[writer] = on
        assert off is not None
        for writer in writers:
            last = pairs[writer][-1]
            pairs[writer][-1] = _recorder_summary(off, last["on"], last["disk"])
    summaries = {w: _median_summary(pairs[w]) for w in writers}
    first = writers[0]
    on = runs[first]
    on["recorder"] = summaries[first]
    on["recorder_by_writer"] = summaries
    on["recorder_off"] = offs[-1]
    for writer in writers[1:]:
        on[f"recorder_on_{writer}"] = runs[writer]
    _print_recorder_table(summaries, console)
    return on


def _run_interleaved(
    args: tuple[int, int, float, float],
    writers: list[str],
    repeat: int,
    interleave: float,
    console: Console,
    opts: dict[str, Any],
) -> dict[str, Any]:
    """``repeat`` recording runs per writer, each window in paused/recording phases."""
    phases: dict[str, list[dict[str, Any]]] = {w: [] for w in writers}
    last: dict[str, Any] = {}
    for k in range(repeat):
        for writer in writers:
            if repeat > 1:
                console.print(f"[bold]recorder cost, interleaved: round {k + 1} of {repeat}[/bold]")
            with tempfile.TemporaryDirectory(prefix="posecast-bench-") as tmp:
                last = _run_once(
                    *args,
                    record_dir=Path(tmp),
                    record_writer=writer,
                    console=console,
                    interleave=interleave,
                    **opts,
                )
            phases[writer] += last.get("phases", [])
    summaries = {w: _interleaved_summary(p) for w, p in phases.items()}
    last["recorder_interleaved"] = summaries
    _print_interleaved(summaries, interleave, console)
    return last


@dataclass(frozen=True)
class _Sample:
    """CPU times, the clock and the server's /metrics at one end of the measured window."""

    recorder: float
    server: tuple[float, float]
    load: list[float]
    machine: tuple[float, float, float]
    wall: float
    metrics: dict[str, float] | None


def _sample(server: _Child, load: LoadFleet, port: int | None) -> _Sample:
    recorder = _children_run_time(server.pid)
    cpu = _proc_cpu(server.pid), load.cpu(), _machine_cpu(), time.monotonic()
    return _Sample(recorder, *cpu, metrics=None if port is None else _scrape(port))


def _run_once(
    clients: int,
    room_size: int,
    rate: float,
    duration: float,
    *,
    record_dir: Path | None,
    console: Console,
    record_writer: str = "process",
    warmup: float,
    ramp_rate: float,
    seed: int,
    interleave: float = 0.0,
    procs: int = 1,
    codec: str = "raw",
    server: str = "relay",
    motion: str = DEFAULT_MOTION,
    shed: bool = False,
) -> dict[str, Any]:
    """One measured run; ``record_dir`` turns the server's recorder on.

    With ``interleave`` (and ``record_dir``) the window is cut into phases of
    that many seconds in which the server records or has recording paused
    (``report["phases"]``, see :func:`_interleaved_phases`).
    """
    if clients < 1 or room_size < 1:
        raise ValueError("clients and room_size must be at least 1")
    if not 0 < rate <= 100:
        raise ValueError("rate must be in (0, 100] Hz")
    if duration <= 0 or warmup < 0 or ramp_rate <= 0:
        raise ValueError("duration and ramp_rate must be positive, warmup non-negative")
    _raise_nofile(clients + 256)
    report: dict[str, Any] = {
        "clients": clients,
        "room_size": room_size,
        "rooms": math.ceil(clients / room_size),
        "rate_hz": rate,
        "duration_s": duration,
        "warmup_s": warmup,
        "ramp_per_s": ramp_rate,
        "record": record_dir is not None,
        "record_writer": record_writer if record_dir is not None else None,
        "nproc": os.cpu_count() or 0,
        "server": server,
        "procs": procs,
        "codec": codec,
        # What runs the compact codec here (the children inherit POSECAST_PURE).
        "codec_implementation": _codec.IMPLEMENTATION,
        "motion": motion,
        "shed": shed,
    }
    if server == "baseline":
        server_argv = [sys.executable, "-c", _BASELINE_BOOT, "--rate", f"{rate:g}"]
    else:
        server_argv = _server_argv(rate, record_dir, record_writer, shed)
    result, start, end = _run_children(
        report,
        server_argv,
        seed=seed,
        interleave=interleave if record_dir is not None else 0.0,
        console=console,
    )
    _add_figures(report, result, start, end)
    print_relay_report(report, console)
    return report


def _server_argv(
    rate: float, record_dir: Path | None, record_writer: str, shed: bool = False
) -> list[str]:
    """The command line of the relay under test: ``posecast serve`` on a free port."""
    return [
        sys.executable,
        "-c",
        _SERVER_BOOT,
        "serve",
        "--host",
        "127.0.0.1",
        "--port",
        "0",
        "--rate",
        f"{rate:g}",
        "--min-rate",
        f"{min(5.0, rate):g}",
        "--max-rate",
        f"{max(30.0, rate):g}",
        "--log-level",
        "warning",
        # Every client comes from 127.0.0.1: the bench lifts the count limits
        # (0: no limit) so that they do not cap the load it asks for.
        "--max-connections",
        "0",
        "--max-connections-per-address",
        "0",
        "--max-rooms",
        "0",
        "--max-recorded-rooms",
        "0",
        # ... and the capacity budget, unless the run is about shedding load.
        *([] if shed else [f"--capacity-{k}=0" for k in ("cpu", "lag", "backlog")]),
        *(
            ["--record", str(record_dir), "--record-writer", record_writer]
            if record_dir is not None
            else []
        ),
    ]


def _run_children(
    report: dict[str, Any],
    server_argv: list[str],
    *,
    seed: int,
    interleave: float,
    console: Console,
) -> tuple[dict[str, Any], _Sample, _Sample]:
    """Start the server and the load, ramp up, measure the window, stop both.

    Adds the ramp's figures (and the phases of ``interleave``) and the server's
    exit code to ``report``; returns the load's result and both ends' samples.
    """
    clients, rate = report["clients"], report["rate_hz"]
    warmup, duration, ramp_rate = report["warmup_s"], report["duration_s"], report["ramp_per_s"]
    ramp_s = clients / ramp_rate
    window_timeout = warmup + 60.0
    server: _Child | None = None
    load: LoadFleet | None = None
    what = "baseline" if report["server"] == "baseline" else "relay"
    try:
        with console.status(f"{what} bench: starting the server ...") as status:
            server = _Child("server", server_argv, hash_seed=seed)
            found = _LISTENING.search(
                server.wait_line(lambda line: _LISTENING.search(line) is not None, timeout=30.0)
            )
            assert found is not None
            port = int(found.group(2))
            cfg = {
                "url": f"ws://127.0.0.1:{port}",
                "clients": clients,
                "room_size": report["room_size"],
                "rate": rate,
                "ramp_rate": ramp_rate,
                "seed": seed,
                "codec": report["codec"],
                "motion": report["motion"],
                "window_timeout": window_timeout,
                "hard_timeout": ramp_s + 30.0 + window_timeout + duration + 60.0,
            }
            status.update(
                f"{what} bench: ramping up {clients} clients at {ramp_rate:g}/s "
                f"from {report['procs']} load process(es) ..."
            )
            before = _storm_sample(server, port if what == "relay" else None)
            load = LoadFleet(cfg, report["procs"], seed)
            report["procs"] = len(load.children)
            _ramp(load, report, timeout=ramp_s + 60.0)
            report.update(_storm_figures(before, _storm_sample(server, before.port), clients))
            t0 = time.monotonic() + warmup
            t1 = t0 + duration
            load.tell({"window": [t0, t1]})
            status.update(f"{what} bench: warm-up {warmup:g} s ...")
            _sleep_until(t0)
            status.update(f"{what} bench: measuring for {duration:g} s ...")
            metrics_port = port if report["server"] == "relay" else None
            start = _sample(server, load, metrics_port)
            if interleave > 0:
                status.update(f"relay bench: measuring for {duration:g} s, recording on/off ...")
                report["phases"] = _interleaved_phases(server.pid, port, t1, interleave)
            _sleep_until(t1)
            end = _sample(server, load, metrics_port)
            status.update(f"{what} bench: collecting ...")
            result = load.results(timeout=60.0)
    finally:
        if load is not None:
            load.stop(grace=15.0)
        if server is not None:
            code = server.stop(grace=15.0)
            report["server_exit_code"] = code
    return result, start, end


@dataclass(frozen=True)
class _StormSample:
    """The relay's CPU time, its work on connections not yet members and its late ticks
    (``/metrics``), at one end of the ramp (the join storm)."""

    port: int | None
    wall: float
    cpu: float
    metrics: dict[str, float] | None


def _storm_sample(server: _Child, port: int | None) -> _StormSample:
    metrics = None if port is None else _scrape(port)
    return _StormSample(port, time.monotonic(), sum(_proc_cpu(server.pid)), metrics)


def _storm_figures(a: _StormSample, b: _StormSample, clients: int) -> dict[str, float]:
    """What the join storm (the ramp) cost the relay: its CPU share over the ramp, the
    share spent on connections not yet members, that per client, and the ticks late
    over the capacity's lag budget (all, and those only for the join work), and the p99
    of the members' tick lag meanwhile."""
    wall = b.wall - a.wall
    join = _delta(a.metrics, b.metrics, "posecast_join_cpu_seconds_total")
    return {
        "ramp_server_cpu_pct": 100.0 * (b.cpu - a.cpu) / wall if wall > 0 else math.nan,
        "ramp_join_cpu_pct": 100.0 * join / wall if wall > 0 else math.nan,
        "join_cpu_ms_per_client": 1e3 * join / clients,
        "ramp_ticks_late": _delta(a.metrics, b.metrics, "posecast_ticks_late_total"),
        "ramp_ticks_late_for_joins": _delta(
            a.metrics, b.metrics, "posecast_ticks_late_for_joins_total"
        ),
        # The admitted members' ticks while the storm was refused (the relay's histogram).
        "ramp_tick_lag_p99_ms": 1e3
        * _histogram_quantile(a.metrics, b.metrics, "posecast_tick_lag_seconds", 0.99),
    }


def _ramp(load: LoadFleet, report: dict[str, Any], timeout: float) -> None:
    """Wait for the load to have joined every client it could; into ``report``."""
    ramped = load.ramped(timeout=timeout)
    report.update(join_figures(ramped))
    report["ramp_s"] = float(ramped["ramp_s"])


def _add_figures(
    report: dict[str, Any], result: dict[str, Any], start: _Sample, end: _Sample
) -> None:
    """The load's result and the window's figures (CPU, throughput, /metrics), into ``report``."""
    clients, room_size, rate = report["clients"], report["room_size"], report["rate_hz"]
    wall = end.wall - start.wall
    server_user = end.server[0] - start.server[0]
    server_sys = end.server[1] - start.server[1]
    server_cpu = server_user + server_sys
    load_cpus = [b - a for a, b in zip(start.load, end.load, strict=True)]
    load_cpu = sum(load_cpus)
    recorder_cpu = end.recorder - start.recorder
    delivered = int(result["poses_delivered"])
    snapshots = int(result["snapshots"])
    busy, steal, total = (end.machine[i] - start.machine[i] for i in range(3))
    ncpu = os.cpu_count() or 1
    # Remote poses/s the clients ask for: each gets its room mates' 3 streams at ``rate``.
    full, last = divmod(clients, room_size)
    offered = rate * len(STREAMS) * (full * room_size * (room_size - 1) + last * (last - 1))
    m0, m1 = start.metrics, end.metrics
    report.update(result)
    report.update(
        {
            "server_cpu_s": server_cpu,
            "server_cpu_pct": 100.0 * server_cpu / wall,
            "server_cpu_us_per_pose": 1e6 * server_cpu / delivered if delivered else math.nan,
            "recorder_cpu_s": recorder_cpu,
            "recorder_cpu_us_per_pose": 1e6 * recorder_cpu / delivered if delivered else math.nan,
            "server_cpu_us_per_snapshot": 1e6 * server_cpu / snapshots if snapshots else math.nan,
            "server_sys_pct": 100.0 * server_sys / wall,
            "load_cpu_pct": 100.0 * load_cpu / wall,
            "load_cpu_pct_per_proc": [100.0 * c / wall for c in load_cpus],
            "load_cpu_pct_max": 100.0 * max(load_cpus) / wall,
            "load_cpu_us_per_pose": 1e6 * load_cpu / delivered if delivered else math.nan,
            "machine_cpu_pct": 100.0 * busy / total if total > 0 else math.nan,
            # CPU used by neither the server nor the load (other jobs on this machine).
            "other_cpu_pct": 100.0 * (busy / total * ncpu)
            - 100.0 * (server_cpu + load_cpu + recorder_cpu) / wall
            if total > 0
            else math.nan,
            # Of one core: time the hypervisor ran other guests on our cores. A
            # busy host slows every figure here; compare runs with little of it.
            "steal_pct": 100.0 * steal / total * ncpu if total > 0 else math.nan,
            "poses_per_s": delivered / wall,
            "offered_poses_per_s": offered,
            # What the server would need at full rate, at the CPU cost per pose measured.
            "server_core_demand_pct": 100.0 * server_cpu / delivered * offered
            if delivered
            else math.nan,
            "snapshot_rate_ratio": float(result["snapshots_per_client_s"]) / rate,
            "bytes_per_pose": result["wire_bytes"] / delivered if delivered else math.nan,
            "payload_bytes_per_pose": result["payload_bytes"] / delivered
            if delivered
            else math.nan,
            "metrics_ok": m0 is not None and m1 is not None,
            "skips": _delta(m0, m1, "posecast_snapshot_skips_total"),
            "flood_drops": _delta(m0, m1, "posecast_flood_drops_total"),
            # Stale, future or out-of-bounds captures: an overloaded relay refuses the
            # updates it reads more than --max-capture-age after their capture.
            "updates_refused": _delta(m0, m1, "posecast_updates_refused_total"),
            "server_poses_out": _delta(m0, m1, "posecast_room_poses_out_total"),
            "tick_lag_max_ms_start": _gauge(m0, "posecast_room_tick_lag_max_ms"),
            "tick_lag_max_ms_end": _gauge(m1, "posecast_room_tick_lag_max_ms"),
            # Only if the server exports the histogram (see docs/lab/relay-benchmark.md).
            "metrics_tick_lag_p99_ms": 1e3
            * _histogram_quantile(m0, m1, "posecast_tick_lag_seconds", 0.99),
            "connections_end": _value(m1, "posecast_connections"),
        }
    )
    report["skips_per_s"] = report["skips"] / wall
    report.update(saturation(report))
