"""The relay benchmark's report, printed as a rich table."""

from __future__ import annotations

import math
from typing import Any

from rich.console import Console
from rich.table import Table

#: One line of the table: figure, value, note.
_Row = tuple[str, str, str]

#: A process above this share of one core is saturated.
SATURATED_CPU_PCT = 90.0
#: The load's publisher woke this late (p99): its event loop is behind.
LOOP_BEHIND_MS = 10.0
#: All cores this busy: every process waits for a core, whoever is "the limit".
MACHINE_FULL_PCT = 95.0


def saturation(r: dict[str, Any]) -> dict[str, Any]:
    """Who limited this run: the server, the load generator, the machine, or none.

    The load is saturated when one of its processes used more than
    :data:`SATURATED_CPU_PCT` of a core or its loop woke its publisher more than
    :data:`LOOP_BEHIND_MS` late (p99) while a core was free (on a full machine
    that lateness is noted, not blamed on the load); the server when it used more than
    :data:`SATURATED_CPU_PCT` of a core, skipped snapshots, refused updates,
    closed connections, or its ticks ran more than half a period late (p99, as
    the clients saw them).
    """
    machine = r["machine_cpu_pct"] > MACHINE_FULL_PCT
    load: list[str] = []
    notes: list[str] = []
    if r["load_cpu_pct_max"] > SATURATED_CPU_PCT:
        load.append(f"a load process used {r['load_cpu_pct_max']:.0f} % of a core")
    if r["send_lag_p99_ms"] > LOOP_BEHIND_MS:
        late = f"the load's loop ran {r['send_lag_p99_ms']:.1f} ms late (p99)"
        # On a machine with no idle core every loop wakes late: not the load's doing.
        (notes if machine else load).append(late)
    server: list[str] = []
    if r["server_cpu_pct"] > SATURATED_CPU_PCT:
        server.append(f"the server used {r['server_cpu_pct']:.0f} % of a core")
    if r["skips"] > 0:
        server.append(f"{r['skips']:.0f} snapshots skipped")
    if r.get("updates_refused", 0) > 0:
        server.append(f"{r['updates_refused']:.0f} updates refused (read too late?)")
    if r.get("clients_closed", 0) > 0:
        server.append(f"{r['clients_closed']} connections closed by the server")
    half_period_ms = 500.0 / r["rate_hz"]
    if r["tick_lag_p99_ms"] > half_period_ms:
        server.append(f"ticks ran {r['tick_lag_p99_ms']:.1f} ms late (p99)")
    by = [name for name, hit in (("server", server), ("generator", load)) if hit]
    if machine:
        by.append("machine")
    notes = server + load + notes
    if machine:
        notes.append(f"all cores {r['machine_cpu_pct']:.0f} % busy")
    return {
        "saturated_by": "+".join(by) or "none",
        "server_saturated": bool(server),
        "generator_saturated": bool(load),
        "machine_saturated": machine,
        "saturation_notes": notes,
    }


def _f(x: Any, digits: int = 1) -> str:
    if isinstance(x, float) and x != x:
        return "-"
    return f"{x:,.{digits}f}" if isinstance(x, float) else f"{x:,}"


def print_relay_report(report: dict[str, Any], console: Console) -> None:
    """The report as a two-column rich table."""
    r = report
    what = "baseline (bare broadcast server)" if r.get("server") == "baseline" else "relay"
    table = Table(
        title=(
            f"{what} bench: {r['clients']} clients, rooms of {r['room_size']}, "
            f"{r['rate_hz']:g} Hz, {r.get('codec', 'raw')} updates of "
            f"{r.get('motion', 'static')} motion, "
            f"{r['window_s']:.1f} s measured on {r['nproc']} cores"
            + (f"; codec: {r['codec_implementation']}" if r.get("codec") == "compact" else "")
        ),
        title_justify="left",
    )
    table.add_column("figure")
    table.add_column("value", justify="right")
    table.add_column("note")
    for row in [*_cpu_rows(r), *_timing_rows(r), *_traffic_rows(r)]:
        table.add_row(*row)
    console.print(table)
    notes = "; ".join(r["saturation_notes"])
    if r["generator_saturated"]:
        console.print(
            f"[bold red]the load generator, not (only) the server, was saturated: {notes}. "
            "Figures measure the load as much as the server: add --procs.[/bold red]"
        )
    else:
        console.print(f"saturated by: {r['saturated_by']}" + (f" ({notes})" if notes else ""))


def _join_rows(r: dict[str, Any]) -> list[_Row]:
    """Who joined, who was refused (by the server's error code) and whose join hung."""
    codes = r.get("join_errors") or {}
    refused = ", ".join(f"{n} {code}" for code, n in sorted(codes.items())) or "none"
    steps = sorted(r.get("clients_hung_at", {}).items())
    hung_at = ", ".join(f"{n} at {step}" for step, n in steps)
    rows: list[_Row] = [
        (
            "clients joined / refused / hung",
            f"{r['clients_joined']} / {r.get('clients_refused', 0)} / {r.get('clients_hung', 0)}",
            f"refused: {refused}; hung: no answer to a handshake step in 15 s"
            + (f" ({hung_at})" if hung_at else ""),
        )
    ]
    if codes:
        rows.append(
            (
                "refusal after p50 / p99 / max",
                f"{_f(r['refusal_p50_ms'])} / {_f(r['refusal_p99_ms'])} / "
                f"{_f(r['refusal_max_ms'])} ms",
                "from the client's first byte to the refusal (error or close)",
            )
        )
    if codes.get("server-full"):
        rows.append(
            (
                "server-full after p50 / p99",
                f"{_f(r['server_full_p50_ms'])} / {_f(r['server_full_p99_ms'])} ms",
                f"{r['server_full_within_1s']} of {codes['server-full']} within 1 s; "
                f"TCP connect p99 {_f(r['connect_p99_ms'])} ms, "
                f"websocket upgrade p99 {_f(r['upgrade_p99_ms'])} ms",
            )
        )
        rows.append(
            (
                "during the joins: tick lag p99",
                f"{_f(r.get('ramp_tick_lag_p99_ms', math.nan), 2)} ms",
                f"/metrics over the ramp: the admitted members' ticks; "
                f"{_f(r.get('join_cpu_ms_per_client', math.nan), 2)} ms of relay CPU a join",
            )
        )
    return rows


def _cpu_rows(r: dict[str, Any]) -> list[_Row]:
    """Who joined, and the CPU the server, the load and the rest of the machine used."""
    return [
        *_join_rows(r),
        (
            "server CPU",
            f"{_f(r['server_cpu_pct'])} %",
            f"of one core; {_f(r['server_sys_pct'])} % in the kernel",
        ),
        ("server CPU per pose", f"{_f(r['server_cpu_us_per_pose'], 2)} us", "per remote pose"),
        ("server CPU per snapshot", f"{_f(r['server_cpu_us_per_snapshot'], 1)} us", ""),
        (
            "load CPU, total / busiest process",
            f"{_f(r['load_cpu_pct'])} % / {_f(r['load_cpu_pct_max'])} %",
            f"{r['procs']} load process(es): "
            + ", ".join(f"{x:.0f}" for x in r["load_cpu_pct_per_proc"])
            + f" %; > {SATURATED_CPU_PCT:g} % = it limits",
        ),
        ("load CPU per pose", f"{_f(r['load_cpu_us_per_pose'], 2)} us", "all load processes"),
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
        (
            "server tick lag p99",
            f"{_f(r['metrics_tick_lag_p99_ms'], 2)} ms",
            "/metrics histogram over the window; - if the server has none",
        ),
        (
            "load send lag p99 / max",
            f"{_f(r['send_lag_p99_ms'], 2)} / {_f(r['send_lag_max_ms'], 2)} ms",
            f"the load's publisher waking late; > {LOOP_BEHIND_MS:g} ms = its loop is behind",
        ),
    ]


def _traffic_rows(r: dict[str, Any]) -> list[_Row]:
    """Snapshots, skips, poses delivered, the server's demand, bytes and late sends."""
    return [
        (
            "snapshots / client / s",
            f"{_f(r['snapshots_per_client_s'], 2)} (min {_f(r['snapshots_per_client_s_min'], 2)})",
            f"asked {r['rate_hz']:g}; ratio {_f(r['snapshot_rate_ratio'], 3)}; "
            f"with the ticks that had nothing new: {_f(r.get('ticks_per_client_s', math.nan), 2)} "
            f"(min {_f(r.get('ticks_per_client_s_min', math.nan), 2)})",
        ),
        ("skips", f"{_f(r['skips'], 0)} ({_f(r['skips_per_s'], 1)}/s)", "/metrics"),
        (
            "updates refused",
            _f(r["updates_refused"], 0),
            "/metrics: stale, future or out-of-bounds captures",
        ),
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
            "updates sent late / skipped",
            f"{_f(r['sends_late'])} / {_f(r['send_skips'])}",
            "late: the load fell a period behind; skipped: the socket held > 64 KiB",
        ),
        (
            "frames decoded in full",
            f"{_f(r['decoded_frames'])} ({_f(r['codec_snapshots'])} codec snapshots)",
            f"other frames {_f(r['other_frames'])}, bad {_f(r['bad_frames'])}, "
            f"connections closed {_f(r['clients_closed'])}",
        ),
        (
            "errors from the server / closes",
            ", ".join(f"{k} {v}" for k, v in sorted(r["server_errors"].items())) or "none",
            "; ".join(r["close_reasons"]) or "no connection closed by the server",
        ),
    ]
