"""``posecast demo``: a relay and N bots on loopback, then QoE per interpolator."""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any

import typer

from posecast.cli.cluster import KillOption, NodesOption, kill_drill
from posecast.cli.common import DEFAULT_METHODS, _fail, _tier, console, plain
from posecast.cli.report import demo_next_steps, print_swarm, verdict
from posecast.cli.serve_checks import BudgetDegOption
from posecast.cli.session import (
    AskRateOption,
    BotCountOption,
    Codec,
    CodecOption,
    DurationOption,
    InterpOption,
    JsonOutOption,
    MotionOption,
    SpawnOption,
    _ask_rate,
    _check_bot_args,
    _check_spawn,
    _given,
    _print_ending,
    _rate_text,
    _run_interruptible,
    _write_json,
)

__all__ = ["Scene", "demo"]


class Scene(StrEnum):
    """A scripted live scene for ``demo --scene``."""

    throw_catch = "throw-catch"


RecordFolderOption = Annotated[Path, typer.Option(help="Folder for the session recording (MCAP).")]
NoRecordOption = Annotated[bool, typer.Option("--no-record", help="Do not record.")]
AdaptiveOption = Annotated[
    bool,
    typer.Option(
        "--adaptive",
        help="The relay chooses each bot's snapshot rate from its link (rate auto, up to "
        "--rate if given, else 30 Hz); the session line and the bots table show the rates "
        "it chose, as the relay reports them (GET /rates).",
    ),
]
DemoLinkOption = Annotated[
    str | None,
    typer.Option(
        "--link",
        help="Emulate a network tier (excellent, good, mediocre, poor) on every bot's "
        "downlink in the demo's relay: bandwidth cap, delay, jitter, loss (as serve --link).",
    ),
]


def _demo_rate(text: str) -> tuple[float, bool]:
    """The demo's ``--rate`` (see :func:`_ask_rate`), within its own server's range."""
    from posecast.server.app import ServerConfig

    rate, auto = _ask_rate(text, "demo")
    server_cfg = ServerConfig()  # what run_demo's own server allows
    if not server_cfg.min_rate <= rate <= server_cfg.max_rate:
        raise _fail(
            f"--rate {rate:g} Hz is outside the demo server's range of "
            f"{server_cfg.min_rate:g}-{server_cfg.max_rate:g} Hz"
        )
    return rate, auto


def _adaptive_rate(ctx: typer.Context, rate: str, adaptive: bool) -> tuple[float, bool]:
    """(Hz, auto) of ``--rate``; with ``--adaptive`` an auto rate whose ceiling is
    ``--rate`` (a number or auto:MAX) when given, else the server's highest."""
    if adaptive and not _given(ctx, "rate"):
        from posecast.server.app import ServerConfig

        return ServerConfig().max_rate, True
    hz, auto = _demo_rate(rate)
    return hz, auto or adaptive


def demo(
    ctx: typer.Context,
    bots: BotCountOption = 6,
    rate: AskRateOption = "15",
    duration: DurationOption = 20.0,
    motion: MotionOption = "traces:sample",
    interp_: InterpOption = DEFAULT_METHODS,
    json_out: JsonOutOption = None,
    record: RecordFolderOption = Path("recordings"),
    no_record: NoRecordOption = False,
    codec: CodecOption = Codec.compact,
    view: Annotated[
        bool, typer.Option("--view", help="Serve a live 3D viewer of the demo's room too.")
    ] = False,
    view_port: Annotated[
        int, typer.Option(help="With --view: serve the page on this port (0: any free one).")
    ] = 8080,
    scene: Annotated[
        Scene | None,
        typer.Option(
            help="Play a scripted scene instead of --motion: throw-catch (bot 0 throws "
            "object:drill, bot 1 catches it and hands it back, the others watch; 3 bots "
            "unless --bots); the table gains the object classes (all, flight, catch).",
        ),
    ] = None,
    nodes: NodesOption = 1,
    kill: KillOption = None,
    spawn: SpawnOption = "circle",
    adaptive: AdaptiveOption = False,
    link: DemoLinkOption = None,
    budget_deg: BudgetDegOption = None,
) -> None:
    """The main job: a server and N bots on loopback, then QoE per interpolator."""
    from posecast.demo import run_demo

    if scene is not None:
        if _given(ctx, "motion"):
            raise _fail("give --scene or --motion, not both")
        motion = scene.value
        if not _given(ctx, "bots"):
            bots = 3
    rate_hz, auto = _adaptive_rate(ctx, rate, adaptive)
    methods = _check_bot_args(rate_hz, bots, duration, interp_, motion)
    _check_spawn(spawn, bots)
    if view and not 0 <= view_port <= 65535:
        raise _fail(f"--view-port {view_port} is not a TCP port (0-65535)")
    if link is not None and nodes > 1:
        raise _fail("--link emulates the demo's one relay: give it without --nodes")
    tier = _tier(link, None)

    if not console.is_terminal:  # piped: the progress comes as plain lines
        plain(f"posecast demo: {bots} bots for {duration:g} s on loopback (Ctrl-C ends early)")
    report = _run_interruptible(
        run_demo,
        bots=bots,
        rate=rate_hz,
        auto_rate=auto,
        duration=duration,
        methods=methods,
        motion=motion,
        console=console,
        record_dir=None if no_record else record,
        codec=codec.value,
        view_port=view_port if view else None,
        nodes=nodes,
        kill=kill_drill(kill, nodes, duration),
        spawn=spawn,
        link=tier,
        budget_deg=budget_deg,
    )
    _print_demo(report, bots, rate_hz, auto, duration, motion, link, json_out)


def _print_demo(
    report: dict[str, Any],
    bots: int,
    rate_hz: float,
    auto: bool,
    duration: float,
    motion: str,
    link: str | None,
    json_out: Path | None,
) -> None:
    """The demo's tables, verdict and next steps; exits 130 if interrupted, or with the
    session's exit code when a connection was lost."""
    over = "" if link is None else f", {link} link"
    title = f"{bots} bots at {_rate_text(rate_hz, auto)} for {duration:g} s ({motion}{over})"
    print_swarm(report, f"posecast demo: {title}")
    _print_ending(report)
    if report.get("recording"):
        plain(f"recorded to {report['recording']} (see `posecast info`)")
    _write_json(report, json_out)
    starved, lone = report["starvation"]["starved"], len(report["bots"]) == 1
    mean = report.get("rates", {}).get("mean_hz")
    said: float | str = rate_hz
    if auto:
        said = "the rates the relay chose" + (f" (mean {mean:.1f} Hz)" if mean else "")
    plain(verdict(report["methods"], said, motion, starved, lone=lone))
    for line in demo_next_steps(report.get("recording"), motion):
        plain(line)
    if report["interrupted"]:
        raise typer.Exit(130)
    if report["ending"]["exit_code"]:
        raise typer.Exit(report["ending"]["exit_code"])
