"""The ``posecast`` command line: one entry point for every job.

Subcommands import their machinery lazily so ``posecast --help`` stays fast.
"""

from __future__ import annotations

import errno
import json
import os
import sys
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table
from typer.core import TyperGroup

__all__ = ["app", "main"]


class _PosecastGroup(TyperGroup):
    """The command group: a user-facing error ends the command with one line, no traceback.

    This is the one place that turns :class:`protocol.errors.PosecastError` (and
    ``OSError`` about files and sockets), raised anywhere below a command, also
    inside an ``ExceptionGroup`` from a task group, into ``error: ...`` on stderr
    and an exit code (see :func:`_user_error`). Anything else is a bug and keeps
    its traceback.
    """

    def invoke(self, ctx: Any) -> Any:
        try:
            return super().invoke(ctx)
        except Exception as exc:
            found = _user_error(exc)
            if found is None:
                raise
            raise _fail(*found) from None


app = typer.Typer(
    name="posecast",
    cls=_PosecastGroup,
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
    """Print ``error: MESSAGE`` on stderr (one line); raise the returned Exit.

    Exit codes: 2 for a usage mistake (an argument, option or input file that
    cannot be used), 1 for a failure at run time.
    """
    err_console.print(f"[bold red]error:[/] {escape(message)}", soft_wrap=True)
    return typer.Exit(code)


_PATH_ERRORS = (FileNotFoundError, FileExistsError, IsADirectoryError, NotADirectoryError)


def _user_error(exc: BaseException) -> tuple[str, int] | None:
    """The one line and exit code for a user-facing error; None for anything else.

    A :class:`PosecastError` that is also a ``ValueError`` (a bad file, tier, trace,
    token...) or a refused rate is a usage mistake (2); any other one failed at run
    time (1). An ``OSError`` naming a path that is missing, present or of the
    wrong kind is a usage mistake (2), any other (a taken port, a full disk) 1. An
    exception group counts if all its exceptions do; the first one is reported.
    """
    if isinstance(exc, BaseExceptionGroup):
        found = [_user_error(e) for e in exc.exceptions]
        if not found or any(f is None for f in found):
            return None
        return found[0]
    from protocol.errors import PosecastError

    if isinstance(exc, PosecastError):
        from client.connection import JoinRefused

        if isinstance(exc, JoinRefused):
            message = f"join refused ({exc.code}): {exc.message}"
        else:
            message = str(exc)
        usage = isinstance(exc, ValueError) or getattr(exc, "code", None) == "bad-rate"
        return message, 2 if usage else 1
    if isinstance(exc, OSError) and exc.errno != errno.EPIPE:
        return _os_message(exc), 2 if isinstance(exc, _PATH_ERRORS) else 1
    return None


def _first_leaf(exc: BaseException) -> BaseException:
    """The first exception in a (nested) exception group, or ``exc`` itself."""
    while isinstance(exc, BaseExceptionGroup) and exc.exceptions:
        exc = exc.exceptions[0]
    return exc


def _os_message(exc: OSError) -> str:
    """``PATH: what is wrong`` for a file error, else the error's own text."""
    what = exc.strerror.lower() if exc.strerror else str(exc)
    if exc.filename is not None:
        return f"{exc.filename}: {what}"
    return what


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


def _parse_methods(text: str, live: bool = False) -> list[str]:
    import interp

    methods = [m.strip() for m in text.split(",") if m.strip()]
    known = interp.names()
    unknown = [m for m in methods if m not in known]
    if unknown or not methods:
        raise _fail(f"unknown interpolator(s) {unknown}; known: {', '.join(known)}")
    if live:
        needs = [m for m in methods if interp.info(m).needs_velocity]
        if needs:
            raise _fail(
                f"{', '.join(needs)} need keyframes with velocities, which live sessions do "
                "not carry yet; use them with `posecast compare` or `posecast table1`"
            )
    return methods


def _fmt(x: float, digits: int = 1) -> str:
    return "-" if x != x else f"{x:.{digits}f}"


_QOE_COLUMNS = (
    "pos p50 mm",
    "pos p95 mm",
    "rot p50 deg",
    "rot p95 deg",
    "tip p50 mm",
    "tip p95 mm",
    "stall %",
)


def _qoe_table(title: str, keys: tuple[str, ...]) -> Table:
    """A table with ``keys`` columns then the DESIGN.md QoE columns."""
    table = Table(title=title, title_justify="left")
    for col in keys:
        table.add_column(col)
    for col in _QOE_COLUMNS:
        table.add_column(col, justify="right")
    return table


def _qoe_cells(st: dict[str, float]) -> list[str]:
    return [
        _fmt(st["pos_p50_mm"]),
        _fmt(st["pos_p95_mm"]),
        _fmt(st["rot_p50_deg"], 2),
        _fmt(st["rot_p95_deg"], 2),
        _fmt(st["tip_p50_mm"]),
        _fmt(st["tip_p95_mm"]),
        _fmt(100.0 * st["stall_fraction"], 2),
    ]


def print_comparison(
    title: str, results: dict[float, dict[str, dict[str, dict[str, float]]]]
) -> None:
    """Rich table: one row per (rate, method, device class)."""
    table = _qoe_table(title, ("rate Hz", "method", "class"))
    for rate, methods in results.items():
        for method, classes in methods.items():
            for cls, st in classes.items():
                table.add_row(f"{rate:g}", method, cls, *_qoe_cells(st))
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


def print_swarm(report: dict[str, Any], title: str) -> None:
    """The demo/bots result: QoE per method and class, then bots and wire figures."""
    table = _qoe_table(title, ("method", "class"))
    for method, classes in report["methods"].items():
        for cls, st in classes.items():
            table.add_row(method, cls, *_qoe_cells(st))
        table.add_section()
    console.print(table)
    bots = Table(title="bots", title_justify="left")
    for col in ("id", "name", "keyframes/s", "delay D ms", "render ms/frame", "clock rtt ms"):
        bots.add_column(col, justify="right")
    for b in report["bots"]:
        bots.add_row(
            str(b["id"]),
            b["name"],
            _fmt(b["rate_hz"]),
            _fmt(b["delay_ms"]),
            _fmt(b["render_cpu_ms_per_frame"], 2),
            _fmt(b["clock_rtt_ms"], 2),
        )
    console.print(bots)
    wire = report["wire"]
    console.print(
        f"wire: {wire['bytes_per_pose']:.1f} bytes per remote pose, "
        f"{wire['bytes_per_s'] / 1000:.1f} kB/s per bot downstream"
        + (" (velocity keyframes, 12 B a pose included)" if wire.get("velocity_keyframes") else "")
    )


_SECRET_HELP = "Require tokens signed with this secret (see `posecast token`); visible in ps."
_SECRET_FILE_HELP = "Read the secret from the first line of this file (kept out of ps)."
_LOG_LEVELS = ("debug", "info", "warning", "error")


def _secret(ctx: typer.Context, secret: str | None, secret_file: Path | None) -> str | None:
    """The secret from --secret, --secret-file or their environment variables.

    An option given on the command line wins over the other one's environment
    variable; both given the same way is a usage mistake.
    """
    if secret is not None and secret_file is not None:
        from_env = [
            name
            for name in ("secret", "secret_file")
            if getattr(ctx.get_parameter_source(name), "name", "") == "ENVIRONMENT"
        ]
        if from_env == ["secret"]:
            secret = None
        elif from_env == ["secret_file"]:
            secret_file = None
        else:
            raise _fail("give the secret once: --secret or --secret-file, not both")
    if secret_file is not None:
        try:
            lines = secret_file.read_text(encoding="utf-8").splitlines()
        except (OSError, UnicodeDecodeError) as exc:
            why = exc.strerror.lower() if isinstance(exc, OSError) and exc.strerror else exc
            raise _fail(f"--secret-file {secret_file}: cannot read it ({why})") from None
        secret = lines[0].strip() if lines else ""
        if not secret:
            raise _fail(
                f"--secret-file {secret_file}: the first line is empty; put the secret there"
            )
    elif secret is not None and not secret.strip():
        raise _fail("the secret is empty; give a non-empty --secret or POSECAST_SECRET")
    return secret


@app.command()
def serve(
    ctx: typer.Context,
    host: Annotated[
        str, typer.Option(help="Address to listen on.", envvar="POSECAST_HOST")
    ] = "127.0.0.1",
    port: Annotated[
        int, typer.Option(help="Port, 0..65535 (0: pick a free one).", envvar="POSECAST_PORT")
    ] = 8765,
    rate: Annotated[
        float, typer.Option(help="Default snapshot rate (Hz).", envvar="POSECAST_RATE")
    ] = 20.0,
    min_rate: Annotated[
        float,
        typer.Option(help="Lowest rate a subscriber may ask.", envvar="POSECAST_MIN_RATE"),
    ] = 5.0,
    max_rate: Annotated[
        float,
        typer.Option(help="Highest rate a subscriber may ask.", envvar="POSECAST_MAX_RATE"),
    ] = 30.0,
    secret: Annotated[str | None, typer.Option(help=_SECRET_HELP, envvar="POSECAST_SECRET")] = None,
    secret_file: Annotated[
        Path | None, typer.Option(help=_SECRET_FILE_HELP, envvar="POSECAST_SECRET_FILE")
    ] = None,
    record: Annotated[
        Path | None,
        typer.Option(
            help="Record every room session as MCAP into this folder.", envvar="POSECAST_RECORD"
        ),
    ] = None,
    record_writer: Annotated[
        str,
        typer.Option(
            help="Where the recorder writes: process (a child process, off the relay's CPU "
            "time) or thread (inside the server process).",
            envvar="POSECAST_RECORD_WRITER",
        ),
    ] = "process",
    link: Annotated[
        str | None,
        typer.Option(
            help="Emulate a network tier (excellent, good, mediocre, poor, or one of --tiers) "
            "on every subscriber's downlink: bandwidth cap, delay, jitter, loss.",
            envvar="POSECAST_LINK",
        ),
    ] = None,
    tiers: Annotated[
        Path | None,
        typer.Option(help="TOML tiers merged over the built-in ones.", envvar="POSECAST_TIERS"),
    ] = None,
    log_level: Annotated[
        str, typer.Option(help="debug, info, warning or error.", envvar="POSECAST_LOG_LEVEL")
    ] = "info",
) -> None:
    """Run the relay server until SIGINT/SIGTERM (then close all with 1001, exit 0).

    Every option can also be set by its POSECAST_* environment variable (an
    option on the command line wins). With --record, SIGUSR1 pauses the
    recording of pose updates and SIGUSR2 resumes it (each pause is written
    into the files as a drops record).
    """
    import asyncio
    import logging
    import signal

    from server.app import RelayServer, ServerConfig

    if not 0 <= port <= 65535:
        raise _fail(f"--port must be in 0..65535 (0 picks a free port), not {port}")
    if not 0 < min_rate <= rate <= max_rate:
        raise _fail("need 0 < --min-rate <= --rate <= --max-rate")
    if record_writer not in ("process", "thread"):
        raise _fail(f"--record-writer must be process or thread, not {record_writer!r}")
    if log_level.lower() not in _LOG_LEVELS:
        raise _fail(f"--log-level must be one of {', '.join(_LOG_LEVELS)}, not {log_level!r}")
    if record is not None and record.exists() and not record.is_dir():
        raise _fail(
            f"--record {record} is a file; give a folder for the recordings "
            "(it is created if missing)"
        )
    secret = _secret(ctx, secret, secret_file)
    tier = _tier(link, tiers)
    logging.basicConfig(
        level=log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    cfg = ServerConfig(
        host=host,
        port=port,
        rate=rate,
        min_rate=min_rate,
        max_rate=max_rate,
        secret=secret,
        record_dir=record,
        record_writer="thread" if record_writer == "thread" else "process",
        link=tier,
    )

    async def main() -> None:
        server = RelayServer(cfg)
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, server.stop)
        # kill -USR1 PID pauses the recording of pose updates, kill -USR2 PID resumes it.
        loop.add_signal_handler(signal.SIGUSR1, server.pause_recording)
        loop.add_signal_handler(signal.SIGUSR2, server.resume_recording)

        async def announce() -> None:
            await server.ready.wait()
            access = "token required" if secret else "open (no --secret)"
            print(f"posecast listening on ws://{host}:{server.port} ({access})", flush=True)

        async with asyncio.TaskGroup() as tg:
            tg.create_task(announce())
            await server.run()
        print("posecast stopped", flush=True)

    try:
        _run_async(main())
    except* OSError as eg:
        exc = _first_leaf(eg)
        if not isinstance(exc, OSError) or exc.filename is not None:
            raise  # a file of the recorder: the one line comes from _user_error
        why = os.strerror(exc.errno).lower() if exc.errno else str(exc)
        raise _fail(
            f"cannot listen on {host}:{port}: {why}; is another server running there? "
            "Pick another --port (0 picks a free one)",
            1,
        ) from None


def _tier(name: str | None, path: Path | None) -> Any:
    """The tier called ``name`` (None: no link emulation) from the built-in tiers and
    ``path``; a tiers file is read, and checked, even without a name."""
    from scenarios.network import load_tiers

    known = load_tiers(path) if path is not None or name is not None else {}
    if name is None:
        return None
    if name not in known:
        raise _fail(f"unknown tier {name!r}; known: {', '.join(known)}")
    return known[name]


def _run_async(coro: Any) -> Any:
    """asyncio.run, on uvloop when the platform has it."""
    import asyncio

    try:
        import uvloop
    except ImportError:
        return asyncio.run(coro)
    return uvloop.run(coro)


@app.command()
def token(
    ctx: typer.Context,
    room: Annotated[str, typer.Option(help="Room the token admits to.")],
    user: Annotated[str, typer.Option(help="User name the token is for.")],
    secret: Annotated[
        str | None, typer.Option(help="The server's secret.", envvar="POSECAST_SECRET")
    ] = None,
    secret_file: Annotated[
        Path | None, typer.Option(help=_SECRET_FILE_HELP, envvar="POSECAST_SECRET_FILE")
    ] = None,
    ttl: Annotated[float, typer.Option(help="Validity in seconds.")] = 3600.0,
) -> None:
    """Print an access token for `posecast serve --secret/--secret-file`."""
    import time

    from server.auth import make_token

    key = _secret(ctx, secret, secret_file)
    if key is None:
        raise _fail("give the server's secret: --secret-file PATH, POSECAST_SECRET or --secret")
    print(make_token(key, room, user, ttl, time.time()))


def _check_bot_args(
    rate: float, n: int, duration: float, interp_text: str, motion: str
) -> tuple[str, ...]:
    """Validate what bots and demo share; returns the interpolator names."""
    from scenarios.traces import TraceError, find_traces

    if n < 1:
        raise _fail("the number of bots must be at least 1")
    if duration <= 0:
        raise _fail("--duration must be positive")
    if rate <= 0:
        raise _fail("--rate must be positive")
    # Velocity methods run live: the bots then send and receive velocity keyframes.
    methods = tuple(_parse_methods(interp_text))
    if not motion.startswith("synthetic"):
        try:
            find_traces(motion)
        except TraceError as exc:
            raise _fail(str(exc)) from None
    return methods


@app.command()
def bots(
    url: Annotated[str, typer.Option(help="Server URL, e.g. ws://127.0.0.1:8765.")],
    n: Annotated[int, typer.Option(help="Number of bots.")] = 8,
    room: Annotated[str, typer.Option(help="Room to join.")] = "lobby",
    rate: Annotated[float, typer.Option(help="Snapshot rate each bot asks for (Hz).")] = 10.0,
    send_rate: Annotated[float, typer.Option(help="Rate each bot publishes at (Hz).")] = 30.0,
    interp_: Annotated[
        str, typer.Option("--interp", help="Interpolators rendered side by side.")
    ] = DEFAULT_METHODS,
    motion: Annotated[
        str,
        typer.Option(
            help="traces:sample (bundled), traces:dev, traces:eval (full sets), a CSV or "
            "folder, or synthetic[:orbit]."
        ),
    ] = "traces:sample",
    duration: Annotated[float, typer.Option(help="Seconds to run.")] = 30.0,
    token_: Annotated[str | None, typer.Option("--token", help="Access token.")] = None,
    secret: Annotated[
        str | None, typer.Option(help="Mint a token per bot with this secret instead.")
    ] = None,
    json_out: Annotated[
        Path | None, typer.Option("--json", help="Write the report as JSON.")
    ] = None,
) -> None:
    """Run N headless bots against a server and report QoE per interpolator."""
    import time

    from websockets.exceptions import InvalidURI, WebSocketException

    from client.bot import BotConfig
    from client.swarm import run_bots, swarm_report

    methods = _check_bot_args(rate, n, duration, interp_, motion)
    base = BotConfig(
        url=url,
        room=room,
        rate=rate,
        send_rate=send_rate,
        methods=methods,
        motion=motion,
        duration=duration,
        token=token_,
        name="bot",
    )
    token_for = None
    if secret is not None:
        from server.auth import make_token

        def token_for(i: int) -> str:
            return make_token(secret, room, f"bot{i}", duration + 600, time.time())

    try:
        with console.status(f"{n} bots in room {room!r} for {duration:g} s ..."):
            reports = _run_async(run_bots(base, n, token_for=token_for))
    except* (OSError, InvalidURI, WebSocketException) as eg:
        raise _fail(f"cannot connect to {url}: {eg.exceptions[0]}") from None
    report = swarm_report(reports)
    print_swarm(report, f"{n} bots at {rate:g} Hz for {duration:g} s ({motion})")
    # A starved machine, and a session the server ended early, are said in one line each.
    for line in [report["starvation"]["warning"], *report["ending"]["lines"]]:
        if line:
            console.print(line, markup=False, highlight=False, soft_wrap=True)
    if json_out is not None:
        json_out.write_text(json.dumps(report, indent=2))
        console.print(f"wrote {json_out}")
    if report["ending"]["exit_code"]:  # the connection was lost (or closed for an error)
        raise typer.Exit(report["ending"]["exit_code"])


@app.command()
def demo(
    bots: Annotated[int, typer.Option("--bots", help="Number of bots.")] = 6,
    rate: Annotated[float, typer.Option(help="Snapshot rate each bot asks for (Hz).")] = 15.0,
    duration: Annotated[float, typer.Option(help="Seconds to run.")] = 20.0,
    motion: Annotated[
        str,
        typer.Option(
            help="traces:sample (bundled), traces:dev, traces:eval (full sets), a CSV or "
            "folder, or synthetic[:orbit]."
        ),
    ] = "traces:sample",
    interp_: Annotated[
        str, typer.Option("--interp", help="Interpolators rendered side by side.")
    ] = DEFAULT_METHODS,
    json_out: Annotated[
        Path | None, typer.Option("--json", help="Write the report as JSON.")
    ] = None,
    record: Annotated[Path, typer.Option(help="Folder for the session recording (MCAP).")] = Path(
        "recordings"
    ),
    no_record: Annotated[bool, typer.Option("--no-record", help="Do not record.")] = False,
) -> None:
    """The main job: a server and N bots on loopback, then QoE per interpolator."""
    from server.app import ServerConfig
    from server.demo import run_demo

    methods = _check_bot_args(rate, bots, duration, interp_, motion)
    server_cfg = ServerConfig()  # what run_demo's own server allows
    if not server_cfg.min_rate <= rate <= server_cfg.max_rate:
        raise _fail(
            f"--rate {rate:g} Hz is outside the demo server's range of "
            f"{server_cfg.min_rate:g}-{server_cfg.max_rate:g} Hz"
        )
    report = _run_async(
        run_demo(
            bots=bots,
            rate=rate,
            duration=duration,
            methods=methods,
            motion=motion,
            console=console,
            record_dir=None if no_record else record,
        )
    )
    print_swarm(
        report,
        f"posecast demo: {bots} bots at {rate:g} Hz for {duration:g} s on loopback ({motion}); "
        "errors vs the senders' own samples",
    )
    for line in [report["starvation"]["warning"], *report["ending"]["lines"]]:
        if line:
            console.print(line, markup=False, highlight=False, soft_wrap=True)
    if report.get("recording"):
        console.print(f"recorded to {report['recording']} (see `posecast info`)")
    if json_out is not None:
        json_out.write_text(json.dumps(report, indent=2))
        console.print(f"wrote {json_out}")
    if report["ending"]["exit_code"]:
        raise typer.Exit(report["ending"]["exit_code"])


@bench_app.command("interp")
def bench_interp(
    max_batch: Annotated[int, typer.Option(help="Largest batch size to time.")] = 1_000_000,
) -> None:
    """Poses/s of each interpolator beside scipy, pytransform3d and kingdon."""
    from scenarios.bench_interp import run_interp_bench

    sizes = tuple(b for b in (1, 100, 10_000, 1_000_000) if b <= max_batch)
    run_interp_bench(batch_sizes=sizes, console=console)


@bench_app.command("relay")
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
    from server.bench import run_relay_bench

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


@app.command()
def table1(
    traces: Annotated[
        list[str],
        typer.Option(
            help="traces:dev, traces:eval, a CSV or folder, synthetic[:NAME[:SEED]] or a "
            "suite .toml (repeatable)."
        ),
    ],
    out: Annotated[Path, typer.Option(help="Output folder for table1.md/.json and plots.")],
    rates: Annotated[str, typer.Option(help="Rates in Hz (integers): 5-30 or 5,10,15.")] = "5-30",
    methods: Annotated[str, typer.Option(help="Interpolators to compare.")] = DEFAULT_METHODS,
    tiers: Annotated[
        Path | None, typer.Option(help="TOML tiers merged over the built-in ones.")
    ] = None,
    transport: Annotated[
        str, typer.Option(help="Link loss model: datagram (lost) or stream (retransmitted).")
    ] = "datagram",
    link: Annotated[bool, typer.Option(help="Also sweep each tier's link model.")] = True,
    bench: Annotated[bool, typer.Option(help="Measure receiver running time.")] = True,
    plots: Annotated[bool, typer.Option(help="Write PNG plots.")] = True,
    seed: Annotated[int, typer.Option(help="Seed of the link model.")] = 0,
    frontier: Annotated[
        bool, typer.Option(help="Add the error-versus-latency view and its frontier.")
    ] = True,
    frontier_rates: Annotated[
        str | None, typer.Option(help="Rates for the latency view (default: the tiers').")
    ] = None,
    live: Annotated[
        bool,
        typer.Option(
            "--live",
            help="Also run every tier through the real relay (link emulation) with "
            "trace-driven bots and report live beside offline, with a tolerance.",
        ),
    ] = False,
    live_duration: Annotated[
        float, typer.Option(help="--live: seconds each bot runs, per tier.")
    ] = 20.0,
    live_bots: Annotated[int, typer.Option(help="--live: bots in the room, per tier.")] = 3,
) -> None:
    """Reproduce the paper's Table 1: QoE vs rate, equal-QoE rates per network tier.

    Also the error-versus-latency view: the headline (hands, p95 tip error)
    against total latency for every method and rate, with and without dead
    reckoning, and the frontier of the best method at each latency. With
    --live, every tier also runs through the real relay and bots, beside its
    offline counterpart ("Live vs offline" in table1.md, key "live" in the JSON);
    the command exits 1 if they disagree beyond the stated tolerance.
    """
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    import interp
    from scenarios.network import TierError, load_tiers
    from scenarios.table1 import describe_rates, run_table1, snapped_range
    from scenarios.traces import TraceError

    rate_list = [int(r) for r in _parse_rates(rates)]
    method_list = _parse_methods(methods)
    if transport not in ("datagram", "stream"):
        raise _fail("--transport must be datagram or stream")
    f_rates = None if frontier_rates is None else [int(r) for r in _parse_rates(frontier_rates)]
    live_cfg: Any = None
    if live:
        # Everything --live needs is checked before the offline sweep starts.
        from server.table1_live import LiveConfig, live_motions

        live_methods = tuple(
            dict.fromkeys(m for m in ["soa", *method_list] if not interp.info(m).needs_velocity)
        )
        try:
            live_cfg = LiveConfig(duration=live_duration, bots=live_bots, methods=live_methods)
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
    command = "posecast table1 " + " ".join(sys.argv[2:])
    bar = Progress(
        TextColumn("{task.description:<24}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total}"),
        TimeElapsedColumn(),
        console=console,
        transient=True,
    )
    tasks: dict[str, Any] = {}

    def progress(stage: str, done: int, total: int) -> None:
        if stage not in tasks:
            tasks[stage] = bar.add_task(stage, total=total)
        bar.update(tasks[stage], completed=done, total=total)

    try:
        with bar:
            report = run_table1(
                traces,
                rate_list,
                method_list,
                tiers,
                out,
                progress,
                seed=seed,
                transport=transport,  # type: ignore[arg-type]
                link=link,
                bench=bench,
                plots=plots,
                command=command,
                frontier=frontier,
                frontier_rates=f_rates,
            )
    except (TraceError, ValueError, KeyError) as exc:
        raise _fail(str(exc)) from None
    live_report: dict[str, Any] | None = None
    if live_cfg is not None:
        import logging

        from scenarios.live_agreement import write_live
        from server.table1_live import run_live

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
                live_report = _run_async(run_live(traces, tier_list, live_cfg, live_progress))
        except (TraceError, ValueError, RuntimeError, OSError, TimeoutError) as exc:
            raise _fail(f"--live: {exc}") from None
        assert live_report is not None
        write_live(out, live_report)
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
    if live_report is not None:
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
    console.print(f"wrote {out}/table1.md, table1.json" + (" and plots" if plots else ""))
    if live_report is not None and not live_report["pass"]:
        bad = [r["tier"] for r in live_report["tiers"] if not r["agreement"]["pass"]]
        err_console.print(
            f"[bold red]live and offline disagree beyond the tolerance[/] in {', '.join(bad)}; "
            f"see {out}/table1.md"
        )
        raise typer.Exit(1)


def _recording(file: Path) -> None:
    """Refuse, in one line, a FILE that is not a posecast recording (exit 2)."""
    from recorder.reader import check_recording

    if file.is_dir():
        raise _fail(f"{file} is a directory; give a recording file (.mcap) in it")
    if not file.exists():
        raise _fail(f"{file}: no such recording")
    if not file.is_file():
        raise _fail(f"{file} is not a regular file; give a recording file (.mcap)")
    check_recording(file)  # a FormatError becomes its one line in _PosecastGroup


@app.command()
def info(
    file: Annotated[Path, typer.Argument(help="A session recording (.mcap or .mcap.part).")],
    json_out: Annotated[bool, typer.Option("--json", help="Print JSON instead of text.")] = False,
) -> None:
    """Users, streams, durations, rates, sizes and drops of a recording."""
    from recorder import format_info
    from recorder import info as recording_info

    _recording(file)
    try:
        data = recording_info(file)
    except Exception as exc:  # a damaged file: say so, suggest recovery
        raise _fail(f"{file}: cannot read ({exc}); try `posecast recover {file}`") from None
    if json_out:
        print(json.dumps(data, indent=2, default=str))
    else:
        print(format_info(data))


@app.command()
def recover(
    file: Annotated[Path, typer.Argument(help="A leftover NAME.mcap.part (or damaged .mcap).")],
    out: Annotated[Path | None, typer.Option(help="Output file (default: NAME.mcap).")] = None,
    overwrite: Annotated[bool, typer.Option(help="Replace an existing output file.")] = False,
) -> None:
    """Recover every intact chunk of a crashed or damaged recording into a complete MCAP."""
    from recorder import recover as recover_file

    _recording(file)  # nothing is written for a file that is not a recording
    try:
        report = recover_file(file, out, overwrite=overwrite)
    except (OSError, ValueError) as exc:
        raise _fail(f"{file}: {exc}") from None
    print(report.summary())


@app.command()
def replay(
    file: Annotated[Path, typer.Argument(help="A session recording (.mcap).")],
    url: Annotated[
        str | None, typer.Option(help="Replay into this live server (ws://HOST:PORT).")
    ] = None,
    speed: Annotated[str, typer.Option(help="Live: 1, 10, ... or max.")] = "1",
    room: Annotated[
        str | None, typer.Option(help="Live: room (default: the recorded one).")
    ] = None,
    token_: Annotated[str | None, typer.Option("--token", help="Live: access token.")] = None,
    offline: Annotated[bool, typer.Option(help="Reconstruct headlessly instead.")] = False,
    interp_: Annotated[
        str, typer.Option("--interp", help="Offline: interpolators.")
    ] = DEFAULT_METHODS,
    rate: Annotated[float, typer.Option(help="Offline: keyframe rate to sample (Hz).")] = 10.0,
    out: Annotated[
        Path | None, typer.Option(help="Offline: write rendered poses (CSV, NPZ) here.")
    ] = None,
    json_out: Annotated[Path | None, typer.Option("--json", help="Write the report.")] = None,
) -> None:
    """Replay a recording into a live server, or reconstruct it offline with QoE."""
    _recording(file)
    if offline == (url is not None):
        raise _fail("give either --url ws://HOST:PORT (live) or --offline")
    if offline:
        from recorder.replay import replay_offline

        methods = _parse_methods(interp_)
        if rate <= 0:
            raise _fail("--rate must be positive")
        try:
            with console.status(f"reconstructing {file.name} at {rate:g} Hz ..."):
                report = replay_offline(file, methods, rate, out)
        except (OSError, ValueError) as exc:
            raise _fail(f"{file}: {exc}") from None
        print_comparison(
            f"{file.name}: keyframes at {rate:g} Hz, rendered at 90 Hz, vs the recorded streams",
            {rate: report["qoe"]},
        )
        if out is not None:
            console.print(f"rendered poses written to {out}")
    else:
        from websockets.exceptions import InvalidURI, WebSocketException

        from client.replay import replay_live

        factor: float | str
        try:
            factor = "max" if speed == "max" else float(speed)
        except ValueError:
            raise _fail("--speed takes a number or max") from None
        if factor != "max" and float(factor) <= 0:
            raise _fail("--speed must be positive")
        assert url is not None
        try:
            with console.status(f"replaying {file.name} into {url} ..."):
                report = _run_async(
                    replay_live(file, url, factor, room, token=token_)  # type: ignore[arg-type]
                )
        except* (OSError, InvalidURI, WebSocketException) as eg:
            raise _fail(f"cannot connect to {url}: {eg.exceptions[0]}") from None
        lat = report["lateness_ms"]
        console.print(
            f"replayed {report['users']} users, {report['updates_sent']} updates "
            f"({report['updates_merged']} merged) into room {report['room']!r} at speed "
            f"{report['speed']:g}; lateness p50 {lat['p50']:.1f} ms, p95 {lat['p95']:.1f} ms"
        )
    if json_out is not None:
        json_out.write_text(json.dumps(report, indent=2, default=str))
        console.print(f"wrote {json_out}")


@app.command()
def export(
    file: Annotated[Path, typer.Argument(help="A session recording (.mcap).")],
    to: Annotated[str, typer.Option(help="csv, npz or foxglove.")],
    out: Annotated[Path | None, typer.Option(help="Output path (default beside FILE).")] = None,
) -> None:
    """Export a recording as CSV, NPZ, or MCAP with Foxglove frame transforms."""
    from recorder.export import export as export_file

    if to not in ("csv", "npz", "foxglove"):
        raise _fail("--to takes csv, npz or foxglove")
    _recording(file)
    stem = file.name.removesuffix(".part").removesuffix(".mcap")
    target = out or file.with_name(
        {"csv": f"{stem}-csv", "npz": f"{stem}.npz", "foxglove": f"{stem}-foxglove.mcap"}[to]
    )
    try:
        path = export_file(file, to, target)  # type: ignore[arg-type]
    except (OSError, ValueError) as exc:
        raise _fail(f"{file}: {exc}") from None
    console.print(f"wrote {path}")


@app.command()
def analyze(
    file: Annotated[
        Path | None, typer.Argument(help="A session recording (.mcap), or use --trace.")
    ] = None,
    trace: Annotated[
        list[str] | None,
        typer.Option(help="Trace CSV, folder, traces:dev or traces:eval (repeatable)."),
    ] = None,
    keep_every: Annotated[str, typer.Option(help="Decimations, e.g. 2,3.")] = "2,3",
    interp_: Annotated[str, typer.Option("--interp", help="Interpolators.")] = DEFAULT_METHODS,
    json_out: Annotated[Path | None, typer.Option("--json", help="Write results as JSON.")] = None,
) -> None:
    """The paper's Tables 2 and 3: decimate, interpolate the missing frames, score."""
    from recorder.analyze import analyze as run_analysis
    from recorder.analyze import format_analysis
    from scenarios.traces import TraceError

    if (file is None) == (not trace):
        raise _fail("give a recording FILE or --trace, not both")
    try:
        keeps = [int(k) for k in keep_every.split(",") if k.strip()]
    except ValueError:
        raise _fail(f"cannot parse --keep-every {keep_every!r}") from None
    if not keeps or any(k < 2 for k in keeps):
        raise _fail("--keep-every takes integers >= 2")
    methods = _parse_methods(interp_)
    if file is not None and (
        file.name.endswith((".mcap", ".mcap.part"))
        or not (file.is_dir() or file.name.endswith((".csv", ".csv.gz")))
    ):
        _recording(file)  # a trace CSV or folder of them is checked as it is loaded
    source: Any = file if file is not None else trace
    try:
        with console.status("analysing ..."):
            result = run_analysis(source, keeps, methods)
    except (TraceError, OSError, ValueError) as exc:
        raise _fail(str(exc)) from None
    print(format_analysis(result))
    if json_out is not None:
        json_out.write_text(json.dumps(result, indent=2, default=str))
        console.print(f"wrote {json_out}")


@app.command("interpolators")
def list_interpolators() -> None:
    """List the registered interpolators (built-in and plug-ins)."""
    import interp

    for name in interp.names():
        info = interp.info(name)
        console.print(f"[bold]{name}[/]: {info.description}")


def _tune_allocator() -> None:
    """Keep freed large buffers in the process (glibc only).

    Interpolating a batch allocates a few hundred kB of numpy temporaries per
    call. By default glibc serves those with mmap and returns them to the OS
    on free, so every call page-faults its memory in again; measured on
    `posecast bench interp`, that doubles the time of an interpolator at batch
    10k. Raising the mmap and trim thresholds keeps them in the heap.
    """
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        m_trim_threshold, m_mmap_threshold = -1, -3
        libc.mallopt(m_mmap_threshold, 64 << 20)
        libc.mallopt(m_trim_threshold, 256 << 20)
    except (OSError, AttributeError):
        pass  # not glibc: nothing to tune


def main() -> None:
    """Entry point of the ``posecast`` console script."""
    _tune_allocator()
    try:
        app()
    except KeyboardInterrupt:
        sys.exit(130)


if __name__ == "__main__":
    main()
