"""The relay's curve over client counts, and the bare baseline side by side.

``posecast bench relay --clients 100,200,500`` runs one measured run per count
and prints one row each; with ``--baseline`` each count also runs the bare
broadcast server (:mod:`posecast.bench.baseline`) under the same load, right
after the relay, and the row adds the server CPU per delivered pose of both
and their ratio.
"""

from __future__ import annotations

import math
from typing import Any

from rich.console import Console
from rich.table import Table

from posecast.bench.common import DEFAULT_MOTION
from posecast.bench.relay import run_relay_bench
from posecast.bench.report import _f

#: The keys of a row of the curve (``--json``: ``{"curve": [row, ...]}``).
CURVE_KEYS = (
    "clients",
    "clients_joined",
    "relay_p50_ms",
    "relay_p99_ms",
    "tick_lag_p99_ms",
    "tick_lag_p99_ms_clients",
    "tick_lag_max_ms",
    "skips",
    "server_cpu_pct",
    "server_us_per_pose",
    "poses_per_s",
    "generator_cpu_pct",
    "generator_cpu_pct_max",
    "saturated_by",
)
#: Added to each row by ``--baseline``.
BASELINE_KEYS = (
    "baseline_server_cpu_pct",
    "baseline_us_per_pose",
    "baseline_relay_p99_ms",
    "baseline_generator_cpu_pct_max",
    "baseline_saturated_by",
    "relay_over_baseline",
)


def parse_counts(text: str) -> list[int]:
    """``"100,200,500"`` -> [100, 200, 500]; ValueError with a one-line reason."""
    counts: list[int] = []
    for part in text.split(","):
        part = part.strip()
        if not part.isdigit() or int(part) < 1:
            raise ValueError(f"--clients takes positive counts separated by commas, not {text!r}")
        counts.append(int(part))
    return counts


def curve_row(relay: dict[str, Any], baseline: dict[str, Any] | None = None) -> dict[str, Any]:
    """One row of the curve from a relay run's report (and the baseline's at that count)."""
    row: dict[str, Any] = {
        "clients": relay["clients"],
        "clients_joined": relay["clients_joined"],
        "relay_p50_ms": relay["relay_p50_ms"],
        "relay_p99_ms": relay["relay_p99_ms"],
        "tick_lag_p99_ms": relay["metrics_tick_lag_p99_ms"],
        "tick_lag_p99_ms_clients": relay["tick_lag_p99_ms"],
        "tick_lag_max_ms": relay["tick_lag_max_ms_end"],
        "skips": relay["skips"],
        "server_cpu_pct": relay["server_cpu_pct"],
        "server_us_per_pose": relay["server_cpu_us_per_pose"],
        "poses_per_s": relay["poses_per_s"],
        "generator_cpu_pct": relay["load_cpu_pct"],
        "generator_cpu_pct_max": relay["load_cpu_pct_max"],
        "saturated_by": relay["saturated_by"],
    }
    if baseline is not None:
        ours, bare = relay["server_cpu_us_per_pose"], baseline["server_cpu_us_per_pose"]
        row.update(
            {
                "baseline_server_cpu_pct": baseline["server_cpu_pct"],
                "baseline_us_per_pose": bare,
                "baseline_relay_p99_ms": baseline["relay_p99_ms"],
                "baseline_generator_cpu_pct_max": baseline["load_cpu_pct_max"],
                "baseline_saturated_by": baseline["saturated_by"],
                "relay_over_baseline": ours / bare if bare and math.isfinite(bare) else math.nan,
            }
        )
    return row


def run_relay_curve(
    counts: list[int],
    room_size: int,
    rate: float,
    duration: float,
    *,
    baseline: bool = False,
    procs: int = 1,
    codec: str = "raw",
    motion: str = DEFAULT_MOTION,
    console: Console | None = None,
    warmup: float = 5.0,
    ramp_rate: float = 50.0,
    seed: int = 0,
    shed: bool = False,
) -> dict[str, Any]:
    """One relay run per count (and a baseline run after each); the curve and every report.

    Returns ``{"curve": [row, ...], "relay": [report, ...], "baseline": [report, ...]}``
    (rows: :data:`CURVE_KEYS`, plus :data:`BASELINE_KEYS` with ``baseline``). The
    baseline takes raw updates only: with ``codec="compact"`` its load sends raw.
    """
    console = console or Console()
    if not counts:
        raise ValueError("no client count to run")
    opts: dict[str, Any] = {
        "warmup": warmup,
        "ramp_rate": ramp_rate,
        "seed": seed,
        "motion": motion,
    }
    rows: list[dict[str, Any]] = []
    relays: list[dict[str, Any]] = []
    bases: list[dict[str, Any]] = []
    for n in counts:
        relay = run_relay_bench(
            n,
            room_size,
            rate,
            duration,
            procs=procs,
            codec=codec,
            console=console,
            shed=shed,
            **opts,
        )
        relays.append(relay)
        bare = None
        if baseline:
            bare = run_relay_bench(
                n,
                room_size,
                rate,
                duration,
                procs=procs,
                codec="raw",
                server="baseline",
                console=console,
                **opts,
            )
            bases.append(bare)
        rows.append(curve_row(relay, bare))
    print_curve(rows, console, codec=codec)
    return {"curve": rows, "relay": relays, "baseline": bases}


def print_curve(rows: list[dict[str, Any]], console: Console, *, codec: str = "raw") -> None:
    """The curve as one table, a row per client count."""
    with_base = bool(rows) and "baseline_us_per_pose" in rows[0]
    table = Table(
        title=f"relay curve ({codec} updates): one run per client count"
        + ("; bare broadcast baseline beside it" if with_base else ""),
        title_justify="left",
    )
    columns = [
        ("clients", "clients", 0),
        ("relay p50 ms", "relay_p50_ms", 2),
        ("relay p99 ms", "relay_p99_ms", 2),
        ("tick lag p99 ms (/metrics)", "tick_lag_p99_ms", 2),
        ("tick lag p99 ms (clients)", "tick_lag_p99_ms_clients", 2),
        ("skips", "skips", 0),
        ("server CPU %", "server_cpu_pct", 1),
        ("server us/pose", "server_us_per_pose", 2),
        ("poses/s", "poses_per_s", 0),
        ("generator CPU % (max proc)", "generator_cpu_pct", 0),
    ]
    if with_base:
        columns += [
            ("baseline us/pose", "baseline_us_per_pose", 2),
            ("relay / baseline", "relay_over_baseline", 2),
        ]
    for name, _, _ in columns:
        table.add_column(name, justify="right")
    table.add_column("saturated by")
    generator = [key for _, key, _ in columns].index("generator_cpu_pct")
    for row in rows:
        cells = [_f(row[key], digits) for _, key, digits in columns]
        cells[generator] = (
            f"{_f(row['generator_cpu_pct'], 0)} ({_f(row['generator_cpu_pct_max'], 0)})"
        )
        saturated = row["saturated_by"]
        if with_base:
            saturated += f"; baseline: {row['baseline_saturated_by']}"
        table.add_row(*cells, saturated)
    console.print(table)
