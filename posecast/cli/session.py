"""A live session: ``serve``, ``token``, ``bots`` (``demo``: ``cli.demo_cmd``)."""

from __future__ import annotations

import json
import logging
import os
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

if TYPE_CHECKING:
    pass

from posecast.cli.common import (
    DEFAULT_METHODS,
    _fail,
    _first_leaf,
    _parse_methods,
    _run_async,
    _tier,
    connect_error,
    console,
    plain,
)
from posecast.cli.report import print_swarm
from posecast.cli.serve_checks import (
    SERVE_LIMITS,
    AllowOriginOption,
    BudgetDegOption,
    CapacityBacklogOption,
    CapacityCpuOption,
    CapacityLagOption,
    HandshakeTimeoutOption,
    MaxConnectRateOption,
    MaxEventRateOption,
    MaxJoinRateOption,
    StallAfterOption,
    StampLagOption,
    ViewRatesOption,
    allowed_origins,
    check_tls_files,
    cluster_config,
    room_volume,
)
from posecast.cli.serve_checks import (
    check_serve_args as _check_serve_args,
)
from posecast.progress import stop_on_ctrl_c

_SECRET_HELP = "Require tokens signed with this secret (see `posecast token`); visible in ps."
_SECRET_FILE_HELP = "Read the secret from the first line of this file (kept out of ps)."
_LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
_MOTION_HELP = (
    "traces:sample (bundled), traces:dev, traces:eval (full sets), a CSV or folder, "
    "synthetic[:orbit], or throw-catch (the live scene: bot 0 throws object:drill, "
    "bot 1 catches it and hands it back, the others watch)."
)

# The options of `serve`, each with its POSECAST_* environment variable.
HostOption = Annotated[str, typer.Option(help="Address to listen on.", envvar="POSECAST_HOST")]
PortOption = Annotated[
    int, typer.Option(help="Port, 0..65535 (0: pick a free one).", envvar="POSECAST_PORT")
]
RateOption = Annotated[
    float, typer.Option(help="Default snapshot rate (Hz).", envvar="POSECAST_RATE")
]
MinRateOption = Annotated[
    float, typer.Option(help="Lowest rate a subscriber may ask.", envvar="POSECAST_MIN_RATE")
]
MaxRateOption = Annotated[
    float, typer.Option(help="Highest rate a subscriber may ask.", envvar="POSECAST_MAX_RATE")
]
ServeSecretOption = Annotated[str | None, typer.Option(help=_SECRET_HELP, envvar="POSECAST_SECRET")]
SecretFileOption = Annotated[
    Path | None, typer.Option(help=_SECRET_FILE_HELP, envvar="POSECAST_SECRET_FILE")
]
CertfileOption = Annotated[
    Path | None,
    typer.Option(
        help="Serve wss:// (TLS) with this certificate chain (PEM); needs --keyfile.",
        envvar="POSECAST_CERTFILE",
    ),
]
KeyfileOption = Annotated[
    Path | None,
    typer.Option(help="The private key (PEM) of --certfile.", envvar="POSECAST_KEYFILE"),
]
PingIntervalOption = Annotated[
    float,
    typer.Option(
        help="Ping every connection this often (s); 0 turns keepalive off.",
        envvar="POSECAST_PING_INTERVAL",
    ),
]
PingTimeoutOption = Annotated[
    float,
    typer.Option(
        help="Close a connection that has not answered a ping within this (s): a dead "
        "peer is gone after at most --ping-interval + --ping-timeout.",
        envvar="POSECAST_PING_TIMEOUT",
    ),
]
CafileOption = Annotated[
    Path | None,
    typer.Option(help="For wss://: trust the CA certificates in this PEM file."),
]
InsecureOption = Annotated[
    bool,
    typer.Option(
        "--insecure",
        help="For wss://: do not check the server's certificate (tests only: anyone "
        "could be at the other end).",
    ),
]
RecordOption = Annotated[
    Path | None,
    typer.Option(
        help="Record every room session as MCAP into this folder.", envvar="POSECAST_RECORD"
    ),
]
RecordWriterOption = Annotated[
    str,
    typer.Option(
        help="Where the recorder writes: process (a child process, off the relay's CPU "
        "time) or thread (inside the server process).",
        envvar="POSECAST_RECORD_WRITER",
    ),
]
LinkOption = Annotated[
    str | None,
    typer.Option(
        help="Emulate a network tier (excellent, good, mediocre, poor, or one of --tiers) "
        "on every subscriber's downlink: bandwidth cap, delay, jitter, loss.",
        envvar="POSECAST_LINK",
    ),
]
TiersOption = Annotated[
    Path | None,
    typer.Option(help="TOML tiers merged over the built-in ones.", envvar="POSECAST_TIERS"),
]
LogLevelOption = Annotated[
    str, typer.Option(help="debug, info, warning or error.", envvar="POSECAST_LOG_LEVEL")
]
# Limits of serve (docs/guides/security.md); 0 turns a count limit off.
MaxCaptureAgeOption = Annotated[
    float,
    typer.Option(
        help="Refuse updates captured longer ago than this (s).",
        envvar="POSECAST_MAX_CAPTURE_AGE",
    ),
]
MaxCaptureAheadOption = Annotated[
    float,
    typer.Option(
        help="Refuse updates captured later than now plus this (s; clock-sync error).",
        envvar="POSECAST_MAX_CAPTURE_AHEAD",
    ),
]
RoomExtentOption = Annotated[
    float | None,
    typer.Option(
        help="Make the room volume the cube +-this (m) on every axis (instead of --volume).",
        envvar="POSECAST_ROOM_EXTENT",
    ),
]
VolumeOption = Annotated[
    str,
    typer.Option(
        help="Room volume X0,Y0,Z0,X1,Y1,Z1 (m), stated at welcome: positions outside "
        "it are refused, compact codes quantise in it (finer than 0.5 mm).",
        envvar="POSECAST_VOLUME",
    ),
]
MisbehaviourBurstOption = Annotated[
    int,
    typer.Option(
        help="Invalid frames or refused updates a connection may send at once (0: no limit).",
        envvar="POSECAST_MISBEHAVIOUR_BURST",
    ),
]
MisbehaviourRefillOption = Annotated[
    float,
    typer.Option(
        help="... and a second, after that; beyond: close 1008.",
        envvar="POSECAST_MISBEHAVIOUR_REFILL",
    ),
]
JoinTimeoutOption = Annotated[
    float,
    typer.Option(
        help="Close connections not joined within this (s).", envvar="POSECAST_JOIN_TIMEOUT"
    ),
]
MaxConnectionsOption = Annotated[
    int, typer.Option(help="Open connections at most.", envvar="POSECAST_MAX_CONNECTIONS")
]
MaxConnectionsPerAddressOption = Annotated[
    int,
    typer.Option(
        help="Open connections from one address at most.",
        envvar="POSECAST_MAX_CONNECTIONS_PER_ADDRESS",
    ),
]
MaxRoomsOption = Annotated[int, typer.Option(help="Rooms at most.", envvar="POSECAST_MAX_ROOMS")]
MaxMembersOption = Annotated[
    int, typer.Option(help="Members of one room at most.", envvar="POSECAST_MAX_MEMBERS")
]
MaxObjectsOption = Annotated[
    int,
    typer.Option(help="Shared objects of one room at most.", envvar="POSECAST_MAX_OBJECTS"),
]
ClusterOption = Annotated[
    str | None,
    typer.Option(
        help="Join the cluster of relays sharing this NATS (nats://HOST:PORT, or a "
        "comma-separated list of a NATS cluster's servers; JetStream on). A client may "
        "then connect to any node and join any room.",
        envvar="POSECAST_CLUSTER",
    ),
]
NodeOption = Annotated[
    str | None,
    typer.Option(
        help="This node's name in the cluster, unique among live nodes [default: the host name].",
        envvar="POSECAST_NODE",
    ),
]
MaxRecordedRoomsOption = Annotated[
    int,
    typer.Option(help="Rooms recorded at once at most.", envvar="POSECAST_MAX_RECORDED_ROOMS"),
]


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


def serve(
    ctx: typer.Context,
    host: HostOption = "127.0.0.1",
    port: PortOption = 8765,
    rate: RateOption = 20.0,
    min_rate: MinRateOption = 5.0,
    max_rate: MaxRateOption = 30.0,
    secret: ServeSecretOption = None,
    secret_file: SecretFileOption = None,
    record: RecordOption = None,
    record_writer: RecordWriterOption = "process",
    link: LinkOption = None,
    tiers: TiersOption = None,
    log_level: LogLevelOption = "info",
    max_capture_age: MaxCaptureAgeOption = 1.0,
    max_capture_ahead: MaxCaptureAheadOption = 0.25,
    stamp_lag: StampLagOption = 0.025,
    room_extent: RoomExtentOption = None,
    volume: VolumeOption = "-8,-2,-8,8,4,8",
    certfile: CertfileOption = None,
    keyfile: KeyfileOption = None,
    ping_interval: PingIntervalOption = 2.5,
    ping_timeout: PingTimeoutOption = 2.5,
    misbehaviour_burst: MisbehaviourBurstOption = 20,
    misbehaviour_refill: MisbehaviourRefillOption = 5.0,
    join_timeout: JoinTimeoutOption = 5.0,
    handshake_timeout: HandshakeTimeoutOption = 2.0,
    max_connect_rate: MaxConnectRateOption = 100.0,
    max_join_rate: MaxJoinRateOption = 60.0,
    max_event_rate: MaxEventRateOption = 1000.0,
    max_connections: MaxConnectionsOption = 1024,
    max_connections_per_address: MaxConnectionsPerAddressOption = 64,
    max_rooms: MaxRoomsOption = 256,
    max_members: MaxMembersOption = 64,
    max_recorded_rooms: MaxRecordedRoomsOption = 32,
    max_objects: MaxObjectsOption = 64,
    cluster: ClusterOption = None,
    node: NodeOption = None,
    allow_origin: AllowOriginOption = None,
    stall_after: StallAfterOption = 1.0,
    capacity_cpu: CapacityCpuOption = 0.8,
    capacity_lag: CapacityLagOption = 0.025,
    capacity_backlog: CapacityBacklogOption = 32 << 20,
    view_rates: ViewRatesOption = True,
) -> None:
    """Run the relay server until SIGINT/SIGTERM (then close all with 1001, exit 0).

    Every option can also be set by its POSECAST_* environment variable (an
    option on the command line wins). With --record, SIGUSR1 pauses the
    recording of pose updates and SIGUSR2 resumes it (each pause is written
    into the files as a drops record).
    """
    from posecast.server.app import ServerConfig

    _check_serve_args(port, rate, min_rate, max_rate, record, record_writer, log_level)
    check_tls_files(certfile, keyfile)
    given = locals()
    limits = {name: given[name] for name in SERVE_LIMITS}
    if bad := [k for k, v in limits.items() if not v >= 0]:
        raise _fail(f"--{bad[0].replace('_', '-')} must not be negative")
    logging.basicConfig(level=log_level.upper(), format=_LOG_FORMAT)
    cfg = ServerConfig(
        **cluster_config(cluster, node),
        secret=_secret(ctx, secret, secret_file),
        link=_tier(link, tiers),
        host=host,
        port=port,
        rate=rate,
        min_rate=min_rate,
        max_rate=max_rate,
        record_dir=record,
        record_writer="thread" if record_writer == "thread" else "process",
        volume=room_volume(volume, room_extent),
        certfile=certfile,
        keyfile=keyfile,
        allow_origins=allowed_origins(allow_origin),
        **limits,
    )
    _serve_until_stopped(cfg)


def _serve_until_stopped(cfg: Any) -> None:
    """Run a relay with ``cfg`` until a signal stops it; a taken port is one line (exit 1)."""
    try:
        _run_async(_serve_main(cfg))
    except* OSError as eg:
        exc = _first_leaf(eg)
        if not isinstance(exc, OSError) or exc.filename is not None:
            raise  # a file of the recorder: the one line comes from _user_error
        why = os.strerror(exc.errno).lower() if exc.errno else str(exc)
        raise _fail(
            f"cannot listen on {cfg.host}:{cfg.port}: {why}; is another server running there? "
            "Pick another --port (0 picks a free one)",
            1,
        ) from None


async def _serve_main(cfg: Any) -> None:
    """The relay, its signal handlers and the "listening" line, until it stops."""
    import asyncio
    import signal

    from posecast.server.app import RelayServer

    server = RelayServer(cfg)
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, server.stop)
    # kill -USR1 PID pauses the recording of pose updates, kill -USR2 PID resumes it.
    loop.add_signal_handler(signal.SIGUSR1, server.pause_recording)
    loop.add_signal_handler(signal.SIGUSR2, server.resume_recording)

    async def announce() -> None:
        await server.ready.wait()
        access = "token required" if cfg.secret else "open (no --secret)"
        print(f"posecast listening on ws://{cfg.host}:{server.port} ({access})", flush=True)

    async with asyncio.TaskGroup() as tg:
        tg.create_task(announce())
        await server.run()
    print("posecast stopped", flush=True)


def token(
    ctx: typer.Context,
    room: Annotated[str, typer.Option(help="Room the token admits to.")],
    user: Annotated[str, typer.Option(help="User name the token is for.")],
    secret: Annotated[
        str | None, typer.Option(help="The server's secret.", envvar="POSECAST_SECRET")
    ] = None,
    secret_file: SecretFileOption = None,
    ttl: Annotated[float, typer.Option(help="Validity in seconds.")] = 3600.0,
) -> None:
    """Print an access token for `posecast serve --secret/--secret-file`."""
    import time

    from posecast.server.auth import make_token

    key = _secret(ctx, secret, secret_file)
    if key is None:
        raise _fail("give the server's secret: --secret-file PATH, POSECAST_SECRET or --secret")
    print(make_token(key, room, user, ttl, time.time()))


def _given(ctx: typer.Context, name: str) -> bool:
    """Whether option ``name`` was given on the command line (or in the environment)."""
    source = ctx.get_parameter_source(name)
    return getattr(source, "name", "DEFAULT") not in ("DEFAULT", "DEFAULT_MAP")


def _rate_text(rate: float, auto: bool) -> str:
    """How a title names the rate the bots asked for."""
    return f"an auto rate (up to {rate:g} Hz)" if auto else f"{rate:g} Hz"


def _check_bot_args(
    rate: float, n: int, duration: float, interp_text: str, motion: str
) -> tuple[str, ...]:
    """Validate what bots and demo share; returns the interpolator names."""
    from posecast.scenarios.traces import TraceError, find_traces

    if n < 1:
        raise _fail("the number of bots must be at least 1")
    if duration <= 0:
        raise _fail("--duration must be positive")
    if rate <= 0:
        raise _fail("--rate must be positive")
    # Velocity methods run live: the bots then send and receive velocity keyframes.
    methods = tuple(_parse_methods(interp_text))
    if motion == "throw-catch" and n < 2:
        raise _fail("the throw-catch scene needs at least 2 bots (a thrower and a catcher)")
    if motion != "throw-catch" and not motion.startswith("synthetic"):
        try:
            find_traces(motion)
        except TraceError as exc:
            raise _fail(str(exc)) from None
    return methods


# The options of `bots` (and of `demo` where they share one).
UrlOption = Annotated[
    str,
    typer.Option(
        help="Server URL, e.g. ws://127.0.0.1:8765; or relays separated by commas "
        "(ws://a:8765,ws://b:8765): bot i starts on relay i (round-robin) and, when its "
        "relay drops, resumes or rejoins on the next ones in order.",
    ),
]
BotCountOption = Annotated[int, typer.Option(help="Number of bots.")]
RoomOption = Annotated[str, typer.Option(help="Room to join.")]
AskRateOption = Annotated[
    str,
    typer.Option(
        help="Snapshot rate each bot asks for (Hz), or auto (auto:MAX, MAX default 30): "
        "the relay chooses each bot's rate from what its link delivers, up to MAX.",
    ),
]


def _ask_rate(text: str, command: str) -> tuple[float, bool]:
    """``--rate``: (Hz, False) for a number, (the ceiling, True) for auto[:MAX]."""
    head, _, tail = text.strip().partition(":")
    auto = head.lower() == "auto"
    try:
        rate = float((tail or "30") if auto else text)
    except ValueError:
        raise _fail(
            f"posecast {command}: invalid value for '--rate': {text!r} is not a number (Hz) "
            f"nor auto (auto:MAX); see posecast {command} --help"
        ) from None
    return rate, auto


SendRateOption = Annotated[float, typer.Option(help="Rate each bot publishes at (Hz).")]
InterpOption = Annotated[str, typer.Option("--interp", help="Interpolators rendered side by side.")]
MotionOption = Annotated[str, typer.Option(help=_MOTION_HELP)]
SpawnOption = Annotated[
    str,
    typer.Option(
        help="Where each bot stands: circle (facing the centre, neighbours 1.5 m apart; "
        "circle:R for radius R m), grid (grid:S: S m apart, default 2), none (everyone "
        "at the motion's own place) or a JSON file of spawn points. A rigid move: the "
        "QoE is the same. A scripted --scene keeps its own places.",
    ),
]


def _check_spawn(spawn: str, n: int) -> None:
    """A spawn layout that names n points (scenarios.spawn), or a one-line refusal."""
    from posecast.scenarios.spawn import layout_points
    from posecast.scenarios.traces import TraceError

    try:
        layout_points(spawn, n)
    except TraceError as exc:
        raise _fail(f"--spawn: {exc}") from None


DurationOption = Annotated[float, typer.Option(help="Seconds to run.")]
TokenOption = Annotated[str | None, typer.Option("--token", help="Access token.")]
BotSecretOption = Annotated[
    str | None,
    typer.Option(
        help="Mint a token per bot with this secret instead; visible in ps.",
        envvar="POSECAST_SECRET",
    ),
]
JsonOutOption = Annotated[Path | None, typer.Option("--json", help="Write the report as JSON.")]


class Codec(StrEnum):
    """How the bots code their poses, both ways (Join.codec)."""

    compact = "compact"
    raw = "raw"


CodecOption = Annotated[
    Codec,
    typer.Option(
        help="Pose coding both ways: compact (quantised to 0.5 mm / 0.05 deg, "
        "delta-coded: ~12 B a pose up, ~9 B down in a room of 10) or raw (float "
        "records, ~47 B up, ~42 B down; for old clients).",
    ),
]


def bots(
    ctx: typer.Context,
    url: UrlOption,
    n: BotCountOption = 8,
    room: RoomOption = "lobby",
    rate: AskRateOption = "10",
    send_rate: SendRateOption = 30.0,
    interp_: InterpOption = DEFAULT_METHODS,
    motion: MotionOption = "traces:sample",
    duration: DurationOption = 30.0,
    token_: TokenOption = None,
    secret: BotSecretOption = None,
    secret_file: SecretFileOption = None,
    json_out: JsonOutOption = None,
    codec: CodecOption = Codec.compact,
    cafile: CafileOption = None,
    insecure: InsecureOption = False,
    spawn: SpawnOption = "circle",
    budget_deg: BudgetDegOption = None,
) -> None:
    """Run N headless bots against a server and report QoE per interpolator.

    The secret can also come from POSECAST_SECRET or POSECAST_SECRET_FILE (kept
    out of ps); an explicit --token wins over a secret from the environment.
    """
    from posecast.client.bot import BotConfig
    from posecast.client.connection import relay_urls

    try:
        urls = relay_urls(url)
    except ValueError as exc:
        raise _fail(f"--url: {exc}") from None
    rate_hz, auto = _ask_rate(rate, "bots")
    methods = _check_bot_args(rate_hz, n, duration, interp_, motion)
    _check_spawn(spawn, n)
    key = _bot_secret(ctx, token_, secret, secret_file)
    if token_ is not None and n > 1:
        raise _fail(
            "--token names one user, and a user has one connection per room: with --n > 1 "
            "give --secret or --secret-file so that each bot gets a token of its own"
        )
    base = BotConfig(
        url=urls[0],
        urls=urls if len(urls) > 1 else (),
        room=room,
        rate=rate_hz,
        auto_rate=auto,
        budget_deg=budget_deg,
        send_rate=send_rate,
        methods=methods,
        motion=motion,
        duration=duration,
        token=token_,
        name="bot",
        codec=codec.value,
        cafile=None if cafile is None else str(cafile),
        insecure=insecure,
    )
    report = _run_swarm(base, n, _token_minter(key, room, duration), spawn)
    print_swarm(report, f"{n} bots at {_rate_text(rate_hz, auto)} for {duration:g} s ({motion})")
    _print_ending(report)
    _write_json(report, json_out)
    if report["interrupted"]:
        raise typer.Exit(130)
    if report["ending"]["exit_code"]:  # the connection was lost (or closed for an error)
        raise typer.Exit(report["ending"]["exit_code"])


def _bot_secret(
    ctx: typer.Context, token: str | None, secret: str | None, secret_file: Path | None
) -> str | None:
    """The secret the bots mint their tokens with, or None to use ``token`` (or none).

    A --token on the command line wins over a secret from POSECAST_SECRET or
    POSECAST_SECRET_FILE; a secret given as an option wins over --token.
    """
    if token is not None:
        given = [
            name
            for name, value in (("secret", secret), ("secret_file", secret_file))
            if value is not None
            and getattr(ctx.get_parameter_source(name), "name", "") != "ENVIRONMENT"
        ]
        if not given:
            return None
    return _secret(ctx, secret, secret_file)


def _token_minter(secret: str | None, room: str, duration: float) -> Any:
    """``token_for(i)``: a token for bot ``i`` signed with ``secret``; None without one."""
    if secret is None:
        return None
    import time

    from posecast.server.auth import make_token

    def token_for(i: int) -> str:
        return make_token(secret, room, f"bot{i}", duration + 600, time.time())

    return token_for


def _run_swarm(base: Any, n: int, token_for: Any, spawn: str = "none") -> dict[str, Any]:
    """Run ``n`` bots like ``base`` to their end; their swarm report."""
    from websockets.exceptions import InvalidURI, WebSocketException

    from posecast.client.swarm import run_bots, swarm_report
    from posecast.scenarios.traces import TraceError

    async def run() -> tuple[Any, bool]:
        stop = stop_on_ctrl_c(console)
        reports = await run_bots(base, n, token_for=token_for, spawn=spawn, stop=stop)
        return reports, stop.is_set()

    doing = f"{n} bots in room {base.room!r} for {base.duration:g} s (Ctrl-C ends early) ..."
    try:
        if console.is_terminal:
            with console.status(doing):
                reports, interrupted = _run_async(run())
        else:  # piped: a live status would show nothing
            plain(doing)
            reports, interrupted = _run_async(run())
    except* (OSError, InvalidURI, WebSocketException) as eg:
        where = ", ".join(base.relays)
        raise _fail(connect_error(where, _first_leaf(eg))) from None
    except* TraceError as eg:  # e.g. a spawn point that puts a bot outside the volume
        raise _fail(str(eg.exceptions[0])) from None
    report: dict[str, Any] = swarm_report(reports)
    report["interrupted"] = interrupted
    return report


def _run_interruptible(run: Any, **kwargs: Any) -> dict[str, Any]:
    """``run(**kwargs, stop=EVENT)`` to its end; the first Ctrl-C sets the event (the
    run ends early and reports the time run): the report's ``interrupted`` says so."""

    async def main() -> dict[str, Any]:
        stop = stop_on_ctrl_c(console)
        report: dict[str, Any] = await run(**kwargs, stop=stop)
        report["interrupted"] = stop.is_set()
        return report

    result: dict[str, Any] = _run_async(main())
    return result


def _print_ending(report: dict[str, Any]) -> None:
    """A starved machine, bots that reconnected after a drop, and a session the server
    ended early, in one line each."""
    reconnects = report.get("reconnects", {}).get("lines", [])
    for line in [report["starvation"]["warning"], *reconnects, *report["ending"]["lines"]]:
        if line:
            console.print(line, markup=False, highlight=False, soft_wrap=True)


def _write_json(report: dict[str, Any], json_out: Path | None) -> None:
    if json_out is not None:
        json_out.write_text(json.dumps(report, indent=2))
        console.print(f"wrote {json_out}")
