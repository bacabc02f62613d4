"""``posecast bench interp`` and ``posecast bench relay``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from posecast.cli.common import _fail, console


def bench_interp(
    max_batch: Annotated[int, typer.Option(help="Largest batch size to time.")] = 1_000_000,
) -> None:
    """Poses/s of each interpolator beside scipy, pytransform3d and kingdon."""
    from scenarios.bench_interp import run_interp_bench

    sizes = tuple(b for b in (1, 100, 10_000, 1_000_000) if b <= max_batch)
    run_interp_bench(batch_sizes=sizes, console=console)


def bench_relay(
    clients: Annotated[int, typer.Option(help="Load clients (in a separate process).")] = 500,
    room_size: Annotated[int, typer.Option(help="Clients per room.")] = 10,
    rate: Annotated[float, typer.Option(help="Publish and snapshot rate (Hz).")] = 20.0,
    duration: Annotated[float, typer.Option(help="Measured seconds (after warm-up).")] = 30.0,
    record: Annotated[
        bool,
        typer.Option(help="Run twice, recorder off then on, and report its cost (Table 4)."),
    ] = False,
    record_writer: Annotated[
        str,
        typer.Option(
            help="With --record: process, thread, or both (three runs: off, process, thread)."
        ),
    ] = "process",
    repeat: Annotated[
        int,
        typer.Option(
            help="With --record: rounds of off/on runs, alternating; figures are medians."
        ),
    ] = 1,
    interleave: Annotated[
        float,
        typer.Option(
            help=(
                "With --record: instead of separate off and on runs, one recording run per "
                "round whose window pauses and resumes the recording every INTERLEAVE s "
                "(e.g. 2.5); the loss compares paired phases of the same server."
            )
        ),
    ] = 0.0,
    json_out: Annotated[
        Path | None, typer.Option("--json", help="Also write the report as JSON here.")
    ] = None,
) -> None:
    """Relay throughput: server CPU per pose, latency p50/p99, skips, tick lag."""
    from posecast.bench import run_relay_bench

    if clients < 1 or room_size < 1 or rate <= 0 or duration <= 0:
        raise _fail("--clients, --room-size, --rate and --duration must be positive")
    if repeat < 1:
        raise _fail("--repeat must be at least 1")
    if interleave and not record:
        raise _fail("--interleave needs --record")
    if record_writer not in ("process", "thread", "both"):
        raise _fail(f"--record-writer must be process, thread or both, not {record_writer!r}")
    try:
        report = run_relay_bench(
            clients,
            room_size,
            rate,
            duration,
            record=record,
            record_writer=record_writer,
            repeat=repeat,
            console=console,
            interleave=interleave,
        )
    except (ValueError, RuntimeError) as exc:
        raise _fail(str(exc)) from None
    if json_out is not None:
        import json

        json_out.write_text(json.dumps(report, indent=2, default=float) + "\n")
