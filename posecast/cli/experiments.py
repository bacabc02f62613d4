"""Experiments: ``compare``, ``table1``, ``interpolators``, ``velocity-sources``."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.table import Table

from posecast.cli.common import (
    DEFAULT_METHODS,
    _fail,
    _fmt,
    _parse_methods,
    _parse_rates,
    _run_async,
    console,
    err_console,
    print_comparison,
)


def compare(
    trace: Annotated[Path, typer.Option(help="Trace CSV in the vr-traces format.")],
    rates: Annotated[
        str, typer.Option(help="Send rates in Hz: 5,10,15 or 5-30.")
    ] = "5,10,15,20,30",
    interp_: Annotated[
        str, typer.Option("--interp", help="Comma-separated interpolators.")
    ] = DEFAULT_METHODS,
    json_out: Annotated[
        Path | None, typer.Option("--json", help="Also write results as JSON.")
    ] = None,
) -> None:
    """Offline interpolator comparison on one trace (ideal network, one-interval playout)."""
    from posecast.scenarios.compare import run_compare
    from posecast.scenarios.traces import TraceError

    rate_list = _parse_rates(rates)
    methods = _parse_methods(interp_)
    try:
        tr, results = run_compare(trace, rate_list, methods)
    except TraceError as exc:
        raise _fail(str(exc)) from None
    print_comparison(
        f"{tr.name}: {tr.duration:.1f} s at {tr.native_rate:.0f} Hz, ideal network, "
        "one-interval playout (errors vs native samples)",
        results,
    )
    if json_out is not None:
        json_out.write_text(json.dumps({str(k): v for k, v in results.items()}, indent=2))
        console.print(f"wrote {json_out}")


# The options of `table1`.
TracesOption = Annotated[
    list[str],
    typer.Option(
        help="traces:dev, traces:eval, a CSV or folder, synthetic[:NAME[:SEED]] or a "
        "suite .toml (repeatable)."
    ),
]
OutOption = Annotated[Path, typer.Option(help="Output folder for table1.md/.json and plots.")]
RatesOption = Annotated[str, typer.Option(help="Rates in Hz (integers): 5-30 or 5,10,15.")]
MethodsOption = Annotated[str, typer.Option(help="Interpolators to compare.")]
TiersOption = Annotated[Path | None, typer.Option(help="TOML tiers merged over the built-in ones.")]
TransportOption = Annotated[
    str, typer.Option(help="Link loss model: datagram (lost) or stream (retransmitted).")
]
LinkOption = Annotated[bool, typer.Option(help="Also sweep each tier's link model.")]
BenchOption = Annotated[bool, typer.Option(help="Measure receiver running time.")]
PlotsOption = Annotated[bool, typer.Option(help="Write PNG plots.")]
SeedOption = Annotated[int, typer.Option(help="Seed of the link model.")]
FrontierOption = Annotated[
    bool, typer.Option(help="Add the error-versus-latency view and its frontier.")
]
FrontierRatesOption = Annotated[
    str | None, typer.Option(help="Rates for the latency view (default: the tiers').")
]
CodecsOption = Annotated[
    str,
    typer.Option(
        help="Codecs to price each method's equal-QoE rate in bytes/s: raw, compact "
        "(compact measures the codec's snapshot sizes on the traces)."
    ),
]
LiveOption = Annotated[
    bool,
    typer.Option(
        "--live",
        help="Also run every tier through the real relay (link emulation) with "
        "trace-driven bots and report live beside offline, with a tolerance.",
    ),
]
LiveDurationOption = Annotated[float, typer.Option(help="--live: seconds each bot runs, per tier.")]
LiveBotsOption = Annotated[int, typer.Option(help="--live: bots in the room, per tier.")]
LiveAutoOption = Annotated[
    bool,
    typer.Option(
        "--live-auto",
        help="With --live: run every tier once more with the bots asking auto rates (the "
        "relay chooses each one's rate from its link, up to 30 Hz), live beside the tier's "
        "fixed rate; one more session per tier.",
    ),
]
LiveBudgetOption = Annotated[
    float | None,
    typer.Option(
        "--live-budget-deg",
        help="With --live-auto: the auto session's bots also join with this error budget "
        "(degrees of visual angle): the relay sends each peer at the rate its view needs.",
    ),
]


def table1(
    traces: TracesOption,
    out: OutOption,
    rates: RatesOption = "5-30",
    methods: MethodsOption = DEFAULT_METHODS,
    tiers: TiersOption = None,
    transport: TransportOption = "datagram",
    link: LinkOption = True,
    bench: BenchOption = True,
    plots: PlotsOption = True,
    seed: SeedOption = 0,
    frontier: FrontierOption = True,
    frontier_rates: FrontierRatesOption = None,
    codecs: CodecsOption = "raw,compact",
    live: LiveOption = False,
    live_duration: LiveDurationOption = 20.0,
    live_bots: LiveBotsOption = 3,
    live_auto: LiveAutoOption = False,
    live_budget_deg: LiveBudgetOption = None,
) -> None:
    """Reproduce the paper's Table 1: QoE vs rate, equal-QoE rates per network tier.

    Also the error-versus-latency view: the headline (hands, p95 tip error)
    against total latency for every method and rate, with and without dead
    reckoning, and the frontier of the best method at each latency. With
    --live, every tier also runs through the real relay and bots, beside its
    offline counterpart ("Live vs offline" in table1.md, key "live" in the JSON);
    the command exits 1 if they disagree beyond the stated tolerance.
    Ctrl-C prints what was measured by then, writes nothing, and exits 130.
    """
    rate_list, method_list, f_rates = _table1_choices(rates, methods, transport, frontier_rates)
    live_plan = _plan_live(
        live, traces, tiers, method_list, live_duration, live_bots, live_auto, live_budget_deg
    )
    done: dict[str, tuple[int, int]] = {}  # stage -> (done, total), for Ctrl-C's line
    try:
        report = _run_offline(
            traces,
            rate_list,
            method_list,
            tiers,
            out,
            seed=seed,
            transport=transport,
            link=link,
            bench=bench,
            plots=plots,
            frontier=frontier,
            frontier_rates=f_rates,
            codecs=[c.strip() for c in codecs.split(",") if c.strip()],
            done=done,
        )
    except KeyboardInterrupt as exc:
        raise _interrupted_offline(done, exc, method_list) from None
    live_report, interrupted = None, False
    if live_plan is not None:
        try:
            live_report = _run_live_tiers(traces, *live_plan, out)
        except KeyboardInterrupt:
            interrupted = True
    _print_table1(report, method_list)
    if live_report is not None:
        _print_live(live_report)
    console.print(f"wrote {out}/table1.md, table1.json" + (" and plots" if plots else ""))
    if interrupted:
        err_console.print(
            "interrupted during --live: the offline Table 1 above is whole; the live "
            "comparison was not finished and is not in table1.md",
            markup=False,
            highlight=False,
        )
        raise typer.Exit(130)
    if live_report is not None and not live_report["pass"]:
        bad = [r["tier"] for r in live_report["tiers"] if not r["agreement"]["pass"]]
        err_console.print(
            f"[bold red]live and offline disagree beyond the tolerance[/] in {', '.join(bad)}; "
            f"see {out}/table1.md"
        )
        raise typer.Exit(1)


def _interrupted_offline(
    done: dict[str, tuple[int, int]], exc: KeyboardInterrupt, method_list: list[str]
) -> typer.Exit:
    """Ctrl-C during the offline sweep: what was measured by then (Table 1 itself once
    the ideal sweep was done, else the error at each finished rate), which stage it
    reached, that nothing was written, and a shorter run; the Exit (130) to raise."""
    from posecast.scenarios.table1 import Table1Interrupted

    covered = "nothing was measured yet"
    if isinstance(exc, Table1Interrupted) and exc.tiers is not None:
        _print_table1({"config": {"rates": exc.rates}, "tiers": exc.tiers}, method_list)
        covered = "the table above is Table 1 on the ideal network, without running times"
    elif isinstance(exc, Table1Interrupted) and exc.curves:
        _print_curves(exc.curves)
        covered = f"the table above covers {len(exc.curves)} of {len(exc.rates)} rates"
    # Progress counts steps over the whole run: the last stage and the run's count.
    where = "starting"
    if done:
        stage, (d, t) = list(done.items())[-1]
        where = f"in {stage}, step {d} of {t}"
    err_console.print(
        f"interrupted during the offline sweep ({where}): {covered}; Table 1 needs the "
        "whole sweep, so nothing was written; a shorter one: --rates 5,10,15,20,30 "
        "--no-link --no-frontier --no-bench",
        markup=False,
        highlight=False,
    )
    return typer.Exit(130)


def _print_curves(curves: dict[int, Any]) -> None:
    """An interrupted sweep's finished rates: hands p95 tip error (mm) per method."""
    methods = list(next(iter(curves.values())))
    table = Table(
        title="ideal network, hands p95 tip error (mm), rates finished", title_justify="left"
    )
    table.add_column("rate Hz", justify="right")
    for m in methods:
        table.add_column(m, justify="right")
    for rate in sorted(curves):
        cells = [curves[rate][m].get("hands", {}).get("tip_p95_mm", float("nan")) for m in methods]
        table.add_row(str(rate), *(f"{c:.1f}" for c in cells))
    console.print(table)


def _table1_choices(
    rates: str, methods: str, transport: str, frontier_rates: str | None
) -> tuple[list[int], list[str], list[int] | None]:
    """table1's rates, methods and frontier rates (a one-line error for a bad one)."""
    rate_list = [int(r) for r in _parse_rates(rates)]
    method_list = _parse_methods(methods)
    if transport not in ("datagram", "stream"):
        raise _fail("--transport must be datagram or stream")
    f_rates = None if frontier_rates is None else [int(r) for r in _parse_rates(frontier_rates)]
    return rate_list, method_list, f_rates


def _plan_live(
    live: bool,
    traces: list[str],
    tiers: Path | None,
    method_list: list[str],
    live_duration: float,
    live_bots: int,
    live_auto: bool = False,
    live_budget_deg: float | None = None,
) -> tuple[list[Any], Any] | None:
    """The tiers and LiveConfig of --live, checked before the offline sweep starts
    (None: no --live)."""
    if live_auto and not live:
        raise _fail("--live-auto runs beside the live Table 1: give --live too")
    if live_budget_deg is not None and not live_auto:
        raise _fail("--live-budget-deg applies to the auto session: give --live-auto too")
    if not live:
        return None
    from posecast import interp
    from posecast.scenarios.network import TierError, load_tiers
    from posecast.scenarios.traces import TraceError
    from posecast.table1_live import LiveConfig, live_motions

    live_methods = tuple(
        dict.fromkeys(m for m in ["soa", *method_list] if not interp.info(m).needs_velocity)
    )
    try:
        live_cfg = LiveConfig(
            duration=live_duration,
            bots=live_bots,
            methods=live_methods,
            auto=live_auto,
            budget_deg=live_budget_deg,
        )
        live_motions(traces)
        tier_list = list(load_tiers(tiers).values())
    except (TraceError, TierError, ValueError) as exc:
        raise _fail(f"--live: {exc}") from None
    skipped = [m for m in method_list if m not in live_methods]
    if skipped:
        err_console.print(
            f"--live: {', '.join(skipped)} need keyframe velocities, which the live "
            "comparison does not model yet: offline only"
        )
    return tier_list, live_cfg


def _run_offline(
    traces: list[str],
    rate_list: list[int],
    method_list: list[str],
    tiers: Path | None,
    out: Path,
    done: dict[str, tuple[int, int]] | None = None,
    **options: Any,
) -> dict[str, Any]:
    """The offline Table 1 sweep (``options``: run_table1's keywords) under a progress bar
    (plain lines when piped); ``done``: each stage's progress, kept up to date."""
    from rich.progress import BarColumn, TextColumn, TimeElapsedColumn

    from posecast.progress import progress as progress_bar
    from posecast.scenarios.table1 import run_table1
    from posecast.scenarios.traces import TraceError

    command = "posecast table1 " + " ".join(sys.argv[2:])
    bar = progress_bar(
        console,
        TextColumn("{task.description:<24}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total}"),
        TimeElapsedColumn(),
    )
    tasks: dict[str, Any] = {}
    seen = {} if done is None else done

    def progress(stage: str, count: int, total: int) -> None:
        seen[stage] = (count, total)
        if stage not in tasks:
            tasks[stage] = bar.add_task(stage, total=total)
        bar.update(tasks[stage], completed=count, total=total)

    try:
        with bar:
            report: dict[str, Any] = run_table1(
                traces, rate_list, method_list, tiers, out, progress, command=command, **options
            )
    except (TraceError, ValueError, KeyError) as exc:
        raise _fail(str(exc)) from None
    return report


def _run_live_tiers(
    traces: list[str], tier_list: list[Any], live_cfg: Any, out: Path
) -> dict[str, Any]:
    """--live: every tier through the real relay under a progress bar; written into ``out``."""
    import logging

    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from posecast.scenarios.live_agreement import write_live
    from posecast.scenarios.traces import TraceError
    from posecast.table1_live import run_live

    # One open relay per tier on loopback: its "no --secret" warning is noise here.
    logging.getLogger("posecast.server").setLevel(logging.ERROR)

    live_bar = Progress(
        TextColumn("{task.description:<24}"),
        BarColumn(),
        TextColumn("{task.fields[note]}"),
        TimeElapsedColumn(),
        console=console,
        transient=True,
    )
    live_tasks: dict[str, Any] = {}

    def live_progress(stage: str, done: float, total: float) -> None:
        if stage not in live_tasks:
            live_tasks[stage] = live_bar.add_task(stage, total=total, note="")
        note = f"{done:.0f}/{total:.0f} s" if stage.startswith("live") else ""
        live_bar.update(live_tasks[stage], completed=done, total=total, note=note)

    try:
        with live_bar:
            live_report: dict[str, Any] = _run_async(
                run_live(traces, tier_list, live_cfg, live_progress)
            )
    except (TraceError, ValueError, RuntimeError, OSError, TimeoutError) as exc:
        raise _fail(f"--live: {exc}") from None
    assert live_report is not None
    write_live(out, live_report)
    return live_report


def _print_table1(report: dict[str, Any], method_list: list[str]) -> None:
    """Table 1 (equal-QoE rate and saving per tier, beside the paper's) and its notes."""
    from posecast.scenarios.table1 import describe_rates, snapped_range

    searched = report["config"]["rates"]
    table = Table(
        title="Table 1: equal-QoE rate (saving vs SoA), ideal network", title_justify="left"
    )
    table.add_column("tier")
    table.add_column("SoA Hz", justify="right")
    others = [m for m in method_list if m != "soa"]
    for m in others:
        table.add_column(m, justify="right")
    paper = report.get("paper", {})
    paper_tiers = {t["name"]: t for t in paper.get("tiers", [])}
    table.add_column("paper", justify="right")
    snapped = False
    for row in report["tiers"]:
        cells = []
        for m in others:
            r = row["equal_qoe_rate"].get(m)
            sv = row["bandwidth_saving_pct"].get(m)
            mark = "" if snapped_range(r, searched) is None else "≤"
            snapped = snapped or bool(mark)
            cells.append("none" if r is None else f"{mark}{r} ({sv:.0f} %)")
        pt = paper_tiers.get(row["name"])
        claim = "-" if pt is None else f"{pt['ga_rate']} ({pt['bandwidth_saving_pct']} %)"
        table.add_row(row["name"], str(row["soa_rate"]), *cells, claim)
    console.print(table)
    console.print(f"rates swept: {describe_rates(searched)}")
    if snapped:
        console.print(
            "≤: equal-QoE rates are the lowest listed rate meeting the bar; the true "
            "rate may lie between listed rates (1 Hz steps: --rates 5-30)"
        )
    if paper:
        console.print(
            f"paper: its rate for {' and '.join(paper.get('ga_methods', []))} (saving), "
            f"and {paper.get('running_time_saving_pct')} % less running time claimed; "
            f"source: {paper.get('source', '')}"
        )
    for codec, entry in report.get("codecs", {}).get("headline", {}).get("codecs", {}).items():
        b = entry.get("best")
        if b is not None:
            console.print(
                f"fewest bytes/s matching raw SoA at 30 Hz at no more latency, {codec}: "
                f"{b['bytes_per_s']:,.0f} B/s ({b['method']} {b['rate']} Hz; "
                f"{b['saving_pct']:.0f} % fewer); per tier: table1.md"
            )


def _print_live(live_report: dict[str, Any]) -> None:
    """The "Live vs offline" table: per tier its verdict, per method both p95 tip errors."""
    lt = Table(
        title="Live vs offline (equal D): hands p95 tip error (mm), D (ms)",
        title_justify="left",
    )
    for col in ("tier", "verdict", "method", "live", "offline", "D live", "D rule", "failed"):
        lt.add_column(col, justify="left" if col in ("tier", "verdict", "failed") else "right")
    for row in live_report["tiers"]:
        lv, of = row["live"], row["offline"]
        failed = [c["what"] for c in row["agreement"]["checks"] if not c["ok"]]
        for i, m in enumerate(lv["methods"]):
            lt.add_row(
                row["tier"] if i == 0 else "",
                ("[green]pass[/]" if row["agreement"]["pass"] else "[red]FAIL[/]")
                if i == 0
                else "",
                m,
                _fmt(lv["methods"][m].get("hands", {}).get("tip_p95_mm", float("nan"))),
                _fmt(of["methods"].get(m, {}).get("hands", {}).get("tip_p95_mm", float("nan"))),
                _fmt(lv["delay_ms"]) if i == 0 else "",
                _fmt(of["delay_ms"]) if i == 0 else "",
                ", ".join(failed) if i == 0 else "",
            )
        lt.add_section()
    console.print(lt)
    if any("auto" in row for row in live_report["tiers"]):
        _print_live_auto(live_report)


def _print_live_auto(live_report: dict[str, Any]) -> None:
    """--live-auto: per tier, its fixed rate and auto rates, live, side by side."""
    first = live_report["config"]["methods"][0]
    at = Table(
        title=f"Live, fixed vs auto rates: {first} hands p95 tip error (mm) at the bots' D",
        title_justify="left",
    )
    for col in ("tier", "policy", "server Hz", "keyframes/s", "link B/s", "D ms", "p95 mm"):
        at.add_column(col, justify="left" if col in ("tier", "policy") else "right")
    for row in live_report["tiers"]:
        runs = [(f"{row['asked_rate_hz']:g} Hz", row["live"])]
        runs += [("auto", row["auto"])] if "auto" in row else []
        for i, (policy, lv) in enumerate(runs):
            hands = lv["methods"].get(first, {}).get("hands", {})
            at.add_row(
                row["tier"] if i == 0 else "",
                policy,
                _fmt(lv.get("server_rate_mean_hz", lv["server_rate_hz"])),
                _fmt(lv["rate_hz"], 2),
                _fmt(lv["bytes_per_s"], 0),
                _fmt(lv["delay_ms"]),
                _fmt(hands.get("tip_p95_mm", float("nan"))),
            )
        at.add_section()
    console.print(at)


def list_interpolators() -> None:
    """List the registered interpolators (built-in and plug-ins)."""
    from posecast import interp

    for name in interp.names():
        info = interp.info(name)
        console.print(f"[bold]{name}[/]: {info.description}")


def velocity_sources(
    traces: Annotated[
        str, typer.Option(help="traces:dev, traces:eval, traces:sample, a CSV or a folder.")
    ] = "traces:dev",
    rates: Annotated[str, typer.Option(help="Comma-separated send rates (Hz).")] = "10,15,20",
    sources: Annotated[
        str,
        typer.Option(
            help=(
                "Velocity sources, comma-separated, or ';'-separated when a source has "
                "parameters (e.g. 'central;causal:2,1')."
            )
        ),
    ] = "central,causal",
    method: Annotated[str, typer.Option(help="The velocity interpolator.")] = "motor-hermite",
) -> None:
    """Hands' tip error of a velocity interpolator per velocity source (ideal network)."""
    from posecast.scenarios.traces import find_traces, load_trace
    from posecast.scenarios.velocity_sources import compare_velocity_sources

    trace_list = [load_trace(f) for f in find_traces(traces)]
    rate_list = [float(r) for r in rates.split(",")]
    source_list = sources.split(";") if ";" in sources else sources.split(",")
    res = compare_velocity_sources(trace_list, rate_list, source_list, method)
    print(f"{method}, hands tip error p50 / p95 (mm), {traces}, ideal network")
    for source, per_rate in res.items():
        for rate, st in per_rate.items():
            print(f"{source:14s} {rate:5g} Hz  {st['tip_p50_mm']:7.1f} / {st['tip_p95_mm']:7.1f}")
