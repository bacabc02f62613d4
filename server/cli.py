"""The ``posecast`` command line: one entry point for every job.

Subcommands import their machinery lazily so ``posecast --help`` stays fast.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

__all__ = ["app", "main"]

app = typer.Typer(
    name="posecast",
    help=(
        "Networked VR pose streaming: relay server, headless bots, pose interpolators "
        "and a QoE bench."
    ),
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
bench_app = typer.Typer(
    help="Benchmarks that print figures (never pass/fail).", no_args_is_help=True
)
app.add_typer(bench_app, name="bench")

# Off a terminal (CI, pipes) rich would wrap tables at 80 columns.
console = Console(width=None if sys.stdout.isatty() else 160)
err_console = Console(stderr=True, width=None if sys.stderr.isatty() else 200)

DEFAULT_METHODS = "soa,dq-slerp,motor-lerp"


def _fail(message: str, code: int = 2) -> typer.Exit:
    err_console.print(f"[bold red]error:[/] {message}")
    return typer.Exit(code)


def _parse_rates(text: str) -> list[float]:
    """``5,10,15`` or ``5-30`` (1 Hz steps) or a mix."""
    rates: list[float] = []
    try:
        for part in text.split(","):
            part = part.strip()
            if not part:
                continue
            if "-" in part:
                lo, hi = (float(x) for x in part.split("-", 1))
                rates.extend(float(r) for r in range(int(lo), int(hi) + 1))
            else:
                rates.append(float(part))
    except ValueError:
        raise _fail(f"cannot parse rates {text!r}; use e.g. 5,10,15 or 5-30") from None
    if not rates or any(r <= 0 for r in rates):
        raise _fail(f"rates must be positive, got {text!r}")
    return rates


def _parse_methods(text: str) -> list[str]:
    import interp

    methods = [m.strip() for m in text.split(",") if m.strip()]
    known = interp.names()
    unknown = [m for m in methods if m not in known]
    if unknown or not methods:
        raise _fail(f"unknown interpolator(s) {unknown}; known: {', '.join(known)}")
    return methods


def _fmt(x: float, digits: int = 1) -> str:
    return "-" if x != x else f"{x:.{digits}f}"


def print_comparison(
    title: str, results: dict[float, dict[str, dict[str, dict[str, float]]]]
) -> None:
    """Rich table: one row per (rate, method, device class)."""
    table = Table(title=title, title_justify="left")
    for col in ("rate Hz", "method", "class"):
        table.add_column(col)
    for col in (
        "pos p50 mm",
        "pos p95 mm",
        "rot p50 deg",
        "rot p95 deg",
        "tip p50 mm",
        "tip p95 mm",
        "stall %",
    ):
        table.add_column(col, justify="right")
    for rate, methods in results.items():
        for method, classes in methods.items():
            for cls, st in classes.items():
                table.add_row(
                    f"{rate:g}",
                    method,
                    cls,
                    _fmt(st["pos_p50_mm"]),
                    _fmt(st["pos_p95_mm"]),
                    _fmt(st["rot_p50_deg"], 2),
                    _fmt(st["rot_p95_deg"], 2),
                    _fmt(st["tip_p50_mm"]),
                    _fmt(st["tip_p95_mm"]),
                    _fmt(100.0 * st["stall_fraction"], 2),
                )
        table.add_section()
    console.print(table)


@app.command()
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
    from scenarios.compare import run_compare
    from scenarios.traces import TraceError

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


@app.command()
def demo(
    trace: Annotated[
        Path | None, typer.Option(help="Trace for the offline comparison (default: a dev trace).")
    ] = None,
) -> None:
    """The main job: an offline comparison of the interpolators on a dev trace."""
    from scenarios.traces import TraceError, find_traces

    if trace is None:
        try:
            trace = find_traces("traces:dev")[0]
        except TraceError as exc:
            raise _fail(str(exc)) from None
    compare(trace=trace, rates="5,10,15,20,30", interp_=DEFAULT_METHODS, json_out=None)


@bench_app.command("interp")
def bench_interp(
    max_batch: Annotated[int, typer.Option(help="Largest batch size to time.")] = 1_000_000,
) -> None:
    """Poses/s of each interpolator beside scipy, pytransform3d and kingdon."""
    from scenarios.bench_interp import run_interp_bench

    sizes = tuple(b for b in (1, 100, 10_000, 1_000_000) if b <= max_batch)
    run_interp_bench(batch_sizes=sizes, console=console)


@app.command("interpolators")
def list_interpolators() -> None:
    """List the registered interpolators (built-in and plug-ins)."""
    import interp

    for name in interp.names():
        info = interp.info(name)
        console.print(f"[bold]{name}[/]: {info.description}")


def main() -> None:
    """Entry point of the ``posecast`` console script."""
    try:
        app()
    except KeyboardInterrupt:
        sys.exit(130)


if __name__ == "__main__":
    main()
