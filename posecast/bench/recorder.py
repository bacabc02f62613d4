"""The recorder's cost (Table 4): paired off/on runs, interleaved phases, their tables."""

from __future__ import annotations

import math
import os
import signal
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Final

import numpy as np
from rich.console import Console
from rich.table import Table

from posecast.bench.procs import (
    _children_run_time,
    _delta,
    _machine_cpu,
    _run_time,
    _scrape,
    _sleep_until,
)
from posecast.bench.report import _f


def _print_interleaved(
    summaries: Mapping[str, Mapping[str, Any]], interleave: float, console: Console
) -> None:
    table = Table(
        title=(
            "recorder cost (Table 4), interleaved: one recording server, pose recording "
            f"paused and resumed every {interleave:g} s"
        ),
        title_justify="left",
    )
    table.add_column("figure")
    for writer in summaries:
        table.add_column(f"{writer} writer", justify="right")

    def row(name: str, key: str, digits: int) -> None:
        table.add_row(name, *(_f(s.get(key, math.nan), digits) for s in summaries.values()))

    row("phases (pairs)", "phases", 0)
    row("relay CPU per pose, paused (us)", "relay_cpu_us_per_pose_paused", 3)
    row("relay CPU per pose, recording (us)", "relay_cpu_us_per_pose_recording", 3)
    row("writer process CPU per pose, recording (us)", "writer_cpu_us_per_pose_recording", 3)
    row("relay throughput loss, pooled (%)", "throughput_loss_pct_pooled", 2)
    row("relay throughput loss, median of pairs (%)", "throughput_loss_pct", 2)
    row("relay throughput loss, mean of pairs (%)", "throughput_loss_pct_mean", 2)
    row("  standard error of that mean", "throughput_loss_pct_se", 2)
    row(f"quiet pairs (host steal <= {_QUIET_STEAL_PCT:g} % of a core)", "quiet_pairs", 0)
    row("  relay throughput loss, mean of quiet pairs (%)", "throughput_loss_pct_quiet_mean", 2)
    row("  standard error of that mean", "throughput_loss_pct_quiet_se", 2)
    row("  median of quiet pairs (%)", "throughput_loss_pct_quiet_median", 2)
    row("stolen by the host, median / max (% of a core)", "steal_pct_median", 0)
    console.print(table)
    for writer, summary in summaries.items():
        console.print(
            f"{writer} writer: CPU-bound relay throughput loss while recording "
            f"{_f(summary['throughput_loss_pct_mean'], 2)} % +- "
            f"{_f(summary['throughput_loss_pct_se'], 2)} (mean of {summary['pairs']} pairs, "
            f"standard error; median {_f(summary['throughput_loss_pct'], 2)} %; target <= 2 %, "
            "the paper lost 4.9 %); quiet pairs: "
            f"{_f(summary['throughput_loss_pct_quiet_mean'], 2)} % +- "
            f"{_f(summary['throughput_loss_pct_quiet_se'], 2)} ({summary['quiet_pairs']} pairs)"
        )


def _median_summary(rounds: list[dict[str, Any]]) -> dict[str, Any]:
    """The median of each figure over the rounds, with every round's loss kept."""
    out = dict(rounds[-1])
    if len(rounds) > 1:
        for key, value in rounds[-1].items():
            if isinstance(value, float):
                out[key] = float(np.median([r[key] for r in rounds]))
    out["rounds"] = len(rounds)
    losses = [r["throughput_loss_pct"] for r in rounds]
    out["throughput_loss_pct_rounds"] = losses
    out["steal_pct_rounds"] = [
        [r.get("steal_pct_off", math.nan), r.get("steal_pct_on", math.nan)] for r in rounds
    ]
    out["throughput_loss_pct_mean"] = float(np.mean(losses))
    # Standard error of that mean (the rounds are independent pairs).
    out["throughput_loss_pct_se"] = (
        float(np.std(losses, ddof=1) / math.sqrt(len(losses))) if len(losses) > 1 else math.nan
    )
    out["total_cpu_overhead_pct_rounds"] = [r["total_cpu_overhead_pct"] for r in rounds]
    return out


def _disk_figures(files: list[Path]) -> dict[str, Any]:
    """Files, bytes and poses of a run's recordings (read before they are deleted)."""
    from posecast.recorder import info as recording_info

    return {
        "files": len(files),
        "disk_bytes": sum(f.stat().st_size for f in files),
        "poses_on_disk": sum(int(recording_info(f)["sizes"]["poses"]) for f in files),
    }


def _recorder_summary(
    off: Mapping[str, Any], on: Mapping[str, Any], disk_figures: Mapping[str, Any]
) -> dict[str, Any]:
    """Table 4 figures of one recorder-on run against the recorder-off run."""
    disk, poses_on_disk = disk_figures["disk_bytes"], disk_figures["poses_on_disk"]
    cost_off, cost_on = off["server_cpu_us_per_pose"], on["server_cpu_us_per_pose"]
    writer_cost = on["recorder_cpu_us_per_pose"]
    total_on = cost_on + writer_cost
    return {
        "writer": on["record_writer"],
        "server_cpu_us_per_pose_off": cost_off,
        "server_cpu_us_per_pose_on": cost_on,
        "recorder_process_cpu_us_per_pose": writer_cost,
        "total_cpu_us_per_pose_on": total_on,
        # The relay's event loop is one core: when it is CPU-bound its throughput
        # scales with 1 / (its own CPU per pose). A writer process runs on another core.
        "throughput_ratio": cost_off / cost_on if cost_on else math.nan,
        "throughput_loss_pct": 100.0 * (1.0 - cost_off / cost_on) if cost_on else math.nan,
        # Everything the recording costs the machine, wherever it runs.
        "total_cpu_overhead_pct": 100.0 * (total_on / cost_off - 1.0) if cost_off else math.nan,
        "delivered_poses_per_s_off": off["poses_per_s"],
        "delivered_poses_per_s_on": on["poses_per_s"],
        "latency_p99_ms_off": off["latency_p99_ms"],
        "latency_p99_ms_on": on["latency_p99_ms"],
        "steal_pct_off": off.get("steal_pct", math.nan),
        "steal_pct_on": on.get("steal_pct", math.nan),
        "files": disk_figures["files"],
        "disk_bytes": disk,
        "poses_on_disk": poses_on_disk,
        "disk_bytes_per_pose": disk / poses_on_disk if poses_on_disk else math.nan,
    }


def _print_recorder_table(
    summaries: Mapping[str, Mapping[str, Any]],
    console: Console,
) -> None:
    first = next(iter(summaries.values()))
    rounds = int(first["rounds"])
    table = Table(
        title="recorder cost (Table 4): same load, recorder off and on"
        + (f"; medians over {rounds} rounds" if rounds > 1 else ""),
        title_justify="left",
    )
    table.add_column("figure")
    table.add_column("off", justify="right")
    for writer in summaries:
        table.add_column(f"on ({writer} writer)", justify="right")

    def row(name: str, on_key: str, digits: int, off_key: str | None = None) -> None:
        cells = [_f(first[off_key], digits) if off_key else "-"]
        cells += [_f(s.get(on_key, math.nan), digits) for s in summaries.values()]
        table.add_row(name, *cells)

    row(
        "relay process CPU per pose (us)",
        "server_cpu_us_per_pose_on",
        2,
        "server_cpu_us_per_pose_off",
    )
    row("writer process CPU per pose (us)", "recorder_process_cpu_us_per_pose", 2)
    row("delivered poses/s", "delivered_poses_per_s_on", 0, "delivered_poses_per_s_off")
    row("capture->receipt p99 (ms)", "latency_p99_ms_on", 1, "latency_p99_ms_off")
    row("relay throughput loss (%)", "throughput_loss_pct", 1)
    row("total CPU overhead (%)", "total_cpu_overhead_pct", 1)
    row("bytes per pose on disk", "disk_bytes_per_pose", 1)
    console.print(table)
    for writer, summary in summaries.items():
        if summary["rounds"] > 1:
            each = ", ".join(_f(x, 1) for x in summary["throughput_loss_pct_rounds"])
            console.print(
                f"{writer} writer, relay throughput loss per round (%): {each}; "
                f"mean {_f(summary['throughput_loss_pct_mean'], 1)} "
                f"+- {_f(summary['throughput_loss_pct_se'], 1)} (standard error)"
            )
            steal = ", ".join(f"{_f(a, 0)}/{_f(b, 0)}" for a, b in summary["steal_pct_rounds"])
            console.print(f"  stolen by the host per round, off/on (% of a core): {steal}")
        console.print(
            f"{writer} writer: CPU-bound relay throughput with the recorder "
            f"x{_f(summary['throughput_ratio'], 3)} ({_f(summary['throughput_loss_pct'], 1)} % "
            "loss; target <= 2 %, the paper lost 4.4 of 89.6 FPS = 4.9 %); all recording CPU "
            f"together {_f(summary['total_cpu_overhead_pct'], 1)} % of the relay's; "
            f"{_f(summary['disk_bytes_per_pose'], 1)} bytes per pose on disk"
        )


#: Recording state of the phases of an interleaved window, repeating: paused,
#: recording, recording, paused (each pair has one of each, in both orders).
_PHASE_PATTERN: Final = (False, True, True, False)
#: A pair of phases counts as quiet when the host stole at most this much of a
#: core (in %) in each: on a shared virtual machine, steal comes and goes with
#: other guests' load, and a phase with much of it measures them, not us.
_QUIET_STEAL_PCT: Final = 10.0
#: Seconds after a pause or resume before a phase is measured: the writer
#: process finishes what the relay handed it before (batches of <= 0.25 s).
_PHASE_SETTLE: Final = 0.5


def _interleaved_phases(pid: int, port: int, end: float, length: float) -> list[dict[str, Any]]:
    """Pause and resume the recording of server ``pid`` in phases until ``end``.

    The server records when this starts. Each phase sets its state (SIGUSR1
    pauses, SIGUSR2 resumes), waits :data:`_PHASE_SETTLE` s and measures the
    rest: the relay's and its writer process's CPU (their threads' run time
    from ``/proc/*/task/*/schedstat``, in ns), the poses the relay sent
    (its ``posecast_room_poses_out_total``) and the CPU the host stole.
    Same process, same clients, phases seconds apart: what differs between a
    paused and a recording phase is the recording.
    """
    phases: list[dict[str, Any]] = []
    recording = True
    k = 0
    while time.monotonic() + length <= end + 0.5 * _PHASE_SETTLE:
        want = _PHASE_PATTERN[k % len(_PHASE_PATTERN)]
        start = time.monotonic()
        if want != recording:
            os.kill(pid, signal.SIGUSR2 if want else signal.SIGUSR1)
            recording = want
        _sleep_until(start + _PHASE_SETTLE)
        m0, s0, r0, c0, w0 = (
            _scrape(port),
            _run_time(pid),
            _children_run_time(pid),
            _machine_cpu(),
            time.monotonic(),
        )
        _sleep_until(start + length)
        m1, s1, r1, c1, w1 = (
            _scrape(port),
            _run_time(pid),
            _children_run_time(pid),
            _machine_cpu(),
            time.monotonic(),
        )
        poses = _delta(m0, m1, "posecast_room_poses_out_total")
        total = c1[2] - c0[2]
        phases.append(
            {
                "recording": recording,
                "wall_s": w1 - w0,
                "relay_cpu_s": s1 - s0,
                "writer_cpu_s": r1 - r0,
                "poses": poses,
                "relay_cpu_us_per_pose": 1e6 * (s1 - s0) / poses if poses > 0 else math.nan,
                "steal_pct": 100.0 * (c1[1] - c0[1]) / total * (os.cpu_count() or 1)
                if total > 0
                else math.nan,
            }
        )
        k += 1
    if not recording:
        os.kill(pid, signal.SIGUSR2)
    return phases


def _interleaved_summary(phases: list[dict[str, Any]]) -> dict[str, Any]:
    """Table 4 from paired phases: each pair is one paused and one recording phase."""
    losses: list[float] = []
    quiet: list[float] = []
    steals: list[float] = []
    for a, b in zip(phases[0::2], phases[1::2], strict=False):
        paused, recording = (a, b) if b["recording"] else (b, a)
        cost_off = paused["relay_cpu_us_per_pose"]
        cost_on = recording["relay_cpu_us_per_pose"]
        if math.isfinite(cost_off) and math.isfinite(cost_on) and cost_on > 0:
            loss = 100.0 * (1.0 - cost_off / cost_on)
            steal = max(paused["steal_pct"], recording["steal_pct"])
            losses.append(loss)
            steals.append(steal)
            if steal <= _QUIET_STEAL_PCT:
                quiet.append(loss)

    def per_pose(recording: bool, key: str) -> float:
        chosen = [p for p in phases if p["recording"] == recording]
        poses = sum(p["poses"] for p in chosen)
        return 1e6 * sum(p[key] for p in chosen) / poses if poses > 0 else math.nan

    off, on = per_pose(False, "relay_cpu_s"), per_pose(True, "relay_cpu_s")
    n = len(losses)
    return {
        "phases": len(phases),
        "pairs": n,
        "relay_cpu_us_per_pose_paused": off,
        "relay_cpu_us_per_pose_recording": on,
        "writer_cpu_us_per_pose_recording": per_pose(True, "writer_cpu_s"),
        "writer_cpu_us_per_pose_paused": per_pose(False, "writer_cpu_s"),
        # pooled over all phases of each state
        "throughput_loss_pct_pooled": 100.0 * (1.0 - off / on) if on > 0 else math.nan,
        "throughput_loss_pct": float(np.median(losses)) if n else math.nan,
        "throughput_loss_pct_mean": float(np.mean(losses)) if n else math.nan,
        "throughput_loss_pct_se": float(np.std(losses, ddof=1) / math.sqrt(n))
        if n > 1
        else math.nan,
        "throughput_loss_pct_pairs": losses,
        # the host's steal (% of a core), the larger of the pair's two phases
        "steal_pct_pairs": steals,
        # Pairs in which the host stole at most _QUIET_STEAL_PCT of a core in both
        # phases: the figure for a machine of one's own.
        "quiet_steal_pct": _QUIET_STEAL_PCT,
        "quiet_pairs": len(quiet),
        "throughput_loss_pct_quiet_mean": float(np.mean(quiet)) if quiet else math.nan,
        "throughput_loss_pct_quiet_se": float(np.std(quiet, ddof=1) / math.sqrt(len(quiet)))
        if len(quiet) > 1
        else math.nan,
        "throughput_loss_pct_quiet_median": float(np.median(quiet)) if quiet else math.nan,
        "phase_records": phases,
        "steal_pct_max": max((p["steal_pct"] for p in phases), default=math.nan),
        "steal_pct_median": float(np.median([p["steal_pct"] for p in phases]))
        if phases
        else math.nan,
    }
