"""The relay benchmark's report, printed as a rich table."""

from __future__ import annotations

from typing import Any

from rich.console import Console
from rich.table import Table

#: One line of the table: figure, value, note.
_Row = tuple[str, str, str]


def _f(x: Any, digits: int = 1) -> str:
    if isinstance(x, float) and x != x:
        return "-"
    return f"{x:,.{digits}f}" if isinstance(x, float) else f"{x:,}"


def print_relay_report(report: dict[str, Any], console: Console) -> None:
    """The report as a two-column rich table."""
    r = report
    table = Table(
        title=(
            f"relay bench: {r['clients']} clients, rooms of {r['room_size']}, "
            f"{r['rate_hz']:g} Hz, {r['window_s']:.1f} s measured on {r['nproc']} cores"
        ),
        title_justify="left",
    )
    table.add_column("figure")
    table.add_column("value", justify="right")
    table.add_column("note")
    for row in [*_cpu_rows(r), *_timing_rows(r), *_traffic_rows(r)]:
        table.add_row(*row)
    console.print(table)


def _cpu_rows(r: dict[str, Any]) -> list[_Row]:
    """Who joined, and the CPU the server, the load and the rest of the machine used."""
    return [
        ("clients joined / failed", f"{r['clients_joined']} / {r['clients_failed']}", ""),
        (
            "server CPU",
            f"{_f(r['server_cpu_pct'])} %",
            f"of one core; {_f(r['server_sys_pct'])} % in the kernel",
        ),
        ("server CPU per pose", f"{_f(r['server_cpu_us_per_pose'], 2)} us", "per remote pose"),
        ("server CPU per snapshot", f"{_f(r['server_cpu_us_per_snapshot'], 1)} us", ""),
        ("load CPU", f"{_f(r['load_cpu_pct'])} %", "load generator; ~100 % = it limits"),
        (
            "machine CPU / other jobs",
            f"{_f(r['machine_cpu_pct'])} % / {_f(r['other_cpu_pct'])} %",
            "all cores / of one core, neither server nor load",
        ),
        (
            "stolen by the host",
            f"{_f(r['steal_pct'])} %",
            "of one core, given to other virtual machines; high: the figures are noisy",
        ),
    ]


def _timing_rows(r: dict[str, Any]) -> list[_Row]:
    """Latency from capture to receipt, its parts, and the lag of the server's ticks."""
    return [
        (
            "capture->receipt p50 / p99",
            f"{_f(r['latency_p50_ms'], 2)} / {_f(r['latency_p99_ms'], 2)} ms",
            "remote poses; includes the wait for the next tick",
        ),
        (
            "  wait for tick p50 / p99",
            f"{_f(r['hold_p50_ms'], 2)} / {_f(r['hold_p99_ms'], 2)} ms",
            "capture -> due tick, 0..1/rate when unsynchronised",
        ),
        (
            "  relay (due tick->receipt) p50 / p99",
            f"{_f(r['relay_p50_ms'], 2)} / {_f(r['relay_p99_ms'], 2)} ms",
            "the load-dependent part",
        ),
        (
            "tick lag p50 / p99",
            f"{_f(r['tick_lag_p50_ms'], 2)} / {_f(r['tick_lag_p99_ms'], 2)} ms",
            "snapshot send time - grid point",
        ),
        (
            "server tick lag max (start -> end)",
            f"{_f(r['tick_lag_max_ms_start'])} -> {_f(r['tick_lag_max_ms_end'])} ms",
            "/metrics, max over rooms",
        ),
    ]


def _traffic_rows(r: dict[str, Any]) -> list[_Row]:
    """Snapshots, skips, poses delivered, the server's demand, bytes and late sends."""
    return [
        (
            "snapshots / client / s",
            f"{_f(r['snapshots_per_client_s'], 2)} (min {_f(r['snapshots_per_client_s_min'], 2)})",
            f"asked {r['rate_hz']:g}; ratio {_f(r['snapshot_rate_ratio'], 3)}",
        ),
        ("skips", f"{_f(r['skips'], 0)} ({_f(r['skips_per_s'], 1)}/s)", "/metrics"),
        (
            "poses delivered / s",
            _f(r["poses_per_s"], 0),
            f"remote poses; {_f(r['offered_poses_per_s'], 0)} asked for",
        ),
        (
            "server core demand at full rate",
            f"{_f(r['server_core_demand_pct'])} %",
            "CPU per pose x poses asked for; > 100 %: one process cannot keep up",
        ),
        (
            "bytes per pose",
            f"{_f(r['bytes_per_pose'], 1)}",
            f"on the wire incl. ws header and own echo; {_f(r['payload_bytes_per_pose'], 1)} "
            "payload",
        ),
        (
            "updates sent late",
            _f(r["sends_late"]),
            f"send lag p99 {_f(r['send_lag_p99_ms'], 2)} ms",
        ),
    ]
