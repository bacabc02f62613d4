"""The tables of ``posecast bench hostile``: honest QoE and server figures, then the attacker."""

from __future__ import annotations

import math
from typing import Any

from rich.console import Console
from rich.table import Table

__all__ = ["print_hostile_report"]


def _num(value: Any, fmt: str = ".0f") -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return format(value, fmt)


def _with_ratio(value: float, ratio: float, fmt: str) -> str:
    if not math.isfinite(ratio):
        return _num(value, fmt)
    return f"{_num(value, fmt)} ({ratio:.2f}x)"


def _counts(counter: dict[str, Any]) -> str:
    return ", ".join(f"{k} {v}" for k, v in sorted(counter.items(), key=lambda kv: -kv[1])) or "-"


def _honest_table(runs: list[dict[str, Any]], method: str) -> Table:
    table = Table(title=f"honest bots ({method}) and the server, beside the clean run")
    for col in (
        "run",
        "hands p95 tip mm",
        "D ms",
        "rate Hz",
        "RSS MB peak",
        "tick lag max ms",
        "overdue p99 ms",
        "unanswered scrapes",
        "load 1m",
    ):
        table.add_column(col, justify="left" if col == "run" else "right")
    for run in runs:
        h, s, vs = run["honest"], run["server"], run["vs_clean"]
        clean = run["attack"] == "clean"
        table.add_row(
            run.get("label", run["attack"]),
            _num(h["hands_tip_p95_mm"])
            if clean
            else _with_ratio(h["hands_tip_p95_mm"], vs["hands_tip_p95"], ".0f"),
            _num(h["delay_ms"]) if clean else _with_ratio(h["delay_ms"], vs["delay"], ".0f"),
            _num(h["rate_hz"], ".1f") if clean else _with_ratio(h["rate_hz"], vs["rate"], ".1f"),
            _num(s["rss_mb_peak"], ".1f"),
            _num(s["tick_lag_max_ms"], ".1f"),
            _num(s["tick_overdue_p99_ms"], ".1f"),
            f"{s['scrapes_unanswered']}/{s['scrapes']}",
            " ".join(f"{x:.1f}" for x in run.get("load_1m", [])) or "-",
        )
    return table


def _attacker_table(runs: list[dict[str, Any]]) -> Table:
    table = Table(title="what the attacker sent and got")
    for col in ("attack", "sent", "close codes", "error codes", "server counted"):
        table.add_column(col)
    for run in runs:
        got = run.get("attacker")
        if got is None:
            continue
        s = run["server"]
        counted = {
            "frames in": s.get("frames_in"),
            "protocol errors": s.get("protocol_errors"),
            "misbehaviour closes": s.get("misbehaviour_closes"),
            "refused conns": s.get("connections_refused"),
            "join timeouts": s.get("join_timeouts"),
            "updates refused": s.get("updates_refused"),
            "skips": s.get("snapshot_skips"),
            "rooms peak": s.get("rooms_peak"),
        }
        table.add_row(
            run.get("label", run["attack"]),
            f"{sum(got.get('sent', {}).values())} in {got.get('seconds', 0):.1f} s\n"
            + _counts(got.get("sent", {})),
            _counts(got.get("closes", {})),
            _counts(got.get("errors", {})),
            ", ".join(f"{k} {_num(v)}" for k, v in counted.items() if v),
        )
    return table


def _what_held(run: dict[str, Any]) -> str:
    """Issue 29's yes/no figures of a run: the hijack, the victim, the blackholed bot."""
    got, parts = run.get("attacker", {}), []
    hijack = got.get("hijack")
    if hijack is not None:
        tries, accepted = sum(hijack["tries"].values()), sum(hijack["accepted"].values())
        codes = _counts(got.get("errors", {}))
        parts.append(f"hijack refused {tries - accepted}/{tries} ({codes})")
        v = got.get("victim", {})
        parts.append(f"victim resumed {v.get('resumed', 0)}/{got.get('rounds', 0)}")
    moved = run.get("server", {}).get("stamps_moved")
    if got.get("sent", {}).get("lagged-update") and moved is not None:
        parts.append(f"{_num(moved)} of its updates re-stamped by the relay")
    v = run.get("victim")
    if v is not None and v.get("report"):
        back = got.get("bot_back_after_s")
        parts.append(
            f"bot back {_num(back, '.1f')} s after the path died, resumed {v['resumed']}, "
            f"rejoined {v['rejoined']}, stalled {100 * v['stall_share']:.0f} %, '{v['ended']}'"
        )
    return "; ".join(parts) or "-"


def _checks_table(runs: list[dict[str, Any]]) -> Table:
    table = Table(title="relay log, honest bots closed, /healthz, and what held")
    for col in ("run", "tracebacks", "bots closed", "/healthz missed", "/healthz max ms", "held"):
        table.add_column(col, justify="left" if col in ("run", "held") else "right")
    for run in runs:
        s = run["server"]
        table.add_row(
            run.get("label", run["attack"]),
            str(s.get("tracebacks", "-")),
            str(run["honest"].get("closed", "-")),
            f"{s.get('healthz_unanswered', '-')}/{s.get('healthz_polls', '-')}",
            _num(s.get("healthz_max_ms"), ".0f"),
            _what_held(run),
        )
    return table


def print_hostile_report(report: dict[str, Any], console: Console) -> None:
    """The tables, every target met or missed (plainly), and the machine's load."""
    runs = report["runs"]
    console.print(_honest_table(runs, report["config"]["method"]))
    console.print(_attacker_table(runs))
    console.print(_checks_table(runs))
    for run in runs:
        name = run.get("label", run["attack"])
        if "failed" in run["honest"]:
            failed = run["honest"]["failed"]
            console.print(f"{name}: {failed}", markup=False, style="bold red")
        for t in run["targets"]:
            mark = "met" if t["met"] else "[bold red]MISSED[/bold red]"
            console.print(f"{name}: {t['target']}: {_num(t['value'], '.2f')} -> {mark}")
    if report["missed"]:
        console.print(f"[bold red]{len(report['missed'])} target(s) missed[/bold red]")
    load = report.get("load") or []
    if load:
        console.print(f"load average at the end: {' '.join(f'{x:.2f}' for x in load)}")
