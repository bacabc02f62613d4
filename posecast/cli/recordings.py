"""Session recordings: ``info``, ``recover``, ``replay``, ``export``, ``analyze``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any

import typer

from posecast.cli.common import (
    DEFAULT_METHODS,
    _fail,
    _first_leaf,
    _parse_methods,
    _run_async,
    connect_error,
    console,
    print_comparison,
)


def _recording(file: Path) -> None:
    """Refuse, in one line, a FILE that is not a posecast recording (exit 2)."""
    from posecast.recorder.reader import check_recording

    if file.is_dir():
        raise _fail(f"{file} is a directory; give a recording file (.mcap) in it")
    if not file.exists():
        raise _fail(f"{file}: no such recording")
    if not file.is_file():
        raise _fail(f"{file} is not a regular file; give a recording file (.mcap)")
    check_recording(file)  # a FormatError becomes its one line in _PosecastGroup


def info(
    file: Annotated[Path, typer.Argument(help="A session recording (.mcap or .mcap.part).")],
    json_out: Annotated[bool, typer.Option("--json", help="Print JSON instead of text.")] = False,
) -> None:
    """Users, streams, durations, rates, sizes and drops of a recording."""
    from posecast.recorder import format_info
    from posecast.recorder import info as recording_info

    _recording(file)
    try:
        data = recording_info(file)
    except Exception as exc:  # a damaged file: say so, suggest recovery
        raise _fail(f"{file}: cannot read ({exc}); try `posecast recover {file}`") from None
    if json_out:
        print(json.dumps(data, indent=2, default=str))
    else:
        print(format_info(data))


def recover(
    file: Annotated[Path, typer.Argument(help="A leftover NAME.mcap.part (or damaged .mcap).")],
    out: Annotated[Path | None, typer.Option(help="Output file (default: NAME.mcap).")] = None,
    overwrite: Annotated[bool, typer.Option(help="Replace an existing output file.")] = False,
) -> None:
    """Recover every intact chunk of a crashed or damaged recording into a complete MCAP."""
    from posecast.recorder import recover as recover_file

    _recording(file)  # nothing is written for a file that is not a recording
    try:
        report = recover_file(file, out, overwrite=overwrite)
    except (OSError, ValueError) as exc:
        raise _fail(f"{file}: {exc}") from None
    print(report.summary())


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
    start: Annotated[float, typer.Option(help="Start this many seconds into the recording.")] = 0.0,
    duration: Annotated[
        float | None, typer.Option(help="Replay this many seconds (default: to the end).")
    ] = None,
    users: Annotated[
        str | None,
        typer.Option(help="Replay only these users (ids, u-ids or names: u1,u2)."),
    ] = None,
    loop: Annotated[
        bool, typer.Option("--loop", help="Live: replay again and again until Ctrl-C.")
    ] = False,
    codec: Annotated[
        str,
        typer.Option(
            help="Live: compact (quantised to 0.25 mm / 0.034 deg, ~12 B a pose) or raw "
            "(the recorded floats exactly, ~47 B a pose)."
        ),
    ] = "compact",
    object_patience: Annotated[
        float,
        typer.Option(
            help="Live: seconds a bot waits for a shared object to have its recorded owner "
            "before it requests or releases it (then it asks anyway)."
        ),
    ] = 1.0,
    spawn: Annotated[
        str,
        typer.Option(
            help="Live: move recorded user i onto spawn point i of circle, circle:R, grid, "
            "grid:S or a JSON file (see posecast bots --spawn); none: as recorded."
        ),
    ] = "none",
) -> None:
    """Replay a recording into a live server, or reconstruct it offline with QoE."""
    _recording(file)
    _check_replay_args(offline, url, (start, duration, users, loop), codec, object_patience)
    chosen = None if users is None else [u for u in users.split(",") if u.strip()]
    if offline:
        report = _replay_offline(file, interp_, rate, out, (start, duration, chosen))
    else:
        assert url is not None
        span = (start, duration, chosen)
        report = _replay_passes(
            file, url, _speed(speed), room, token_, span, loop, (codec, object_patience, spawn)
        )
        _print_live(report)
    if json_out is not None:
        json_out.write_text(json.dumps(report, indent=2, default=str))
        console.print(f"wrote {json_out}")


def _replay_offline(
    file: Path,
    interp_: str,
    rate: float,
    out: Path | None,
    span: tuple[float, float | None, list[str] | None],
) -> dict[str, Any]:
    """``replay --offline``: reconstruct ``file`` at ``rate`` Hz, print its QoE table."""
    from posecast.recorder.replay import replay_offline

    methods = _parse_methods(interp_)
    if rate <= 0:
        raise _fail("--rate must be positive")
    _check_offline_rate(file, rate)
    start, duration, chosen = span
    try:
        with console.status(f"reconstructing {file.name} at {rate:g} Hz ..."):
            report = replay_offline(
                file, methods, rate, out, start=start, duration=duration, users=chosen
            )
    except (OSError, ValueError) as exc:
        raise _fail(f"{file}: {exc}") from None
    print_comparison(
        f"{file.name}: keyframes at {rate:g} Hz, rendered at 90 Hz, vs the recorded streams",
        {rate: report["qoe"]},
    )
    _print_objects(report)
    if out is not None:
        console.print(f"rendered poses written to {out}")
    return report


def _check_offline_rate(file: Path, rate: float) -> None:
    """Refuse an offline --rate at or above the recording's own keyframe rate: every
    recorded pose would be a keyframe, nothing interpolated, and every error 0."""
    from statistics import median

    from posecast.recorder import info as recording_info

    rates = [s["rate"] for s in recording_info(file)["streams"] if s.get("rate")]
    if not rates:
        return
    recorded = median(rates)
    if rate >= 0.99 * recorded:
        raise _fail(
            f"--rate {rate:g} Hz is not below {file.name}'s own {recorded:.0f} Hz: every "
            "recorded pose would be a keyframe and every error 0; give a lower --rate "
            f"(e.g. {max(1, round(recorded / 3)):g}) to see what interpolation hides"
        )


def _print_objects(report: dict[str, Any]) -> None:
    """An offline replay's shared objects, one line each."""
    for obj in report["objects"]:
        console.print(
            f"{obj['name']}: {obj['keyframes']} keyframes ({obj['flight_keyframes']} in"
            f" flight), {len(obj['changes'])} ownership changes"
        )


def _print_live(report: dict[str, Any]) -> None:
    """A live replay's summary: updates, lateness, shared objects."""
    lat = report["lateness_ms"]
    console.print(
        f"replayed {report['users']} users, {report['updates_sent']} updates "
        f"({report['updates_merged']} merged) into room {report['room']!r} at speed "
        f"{report['speed']:g}; lateness p50 {lat['p50']:.1f} ms, p95 {lat['p95']:.1f} ms"
    )
    objects = report["objects"]
    if objects["actions_recorded"]:
        console.print(
            f"shared objects: {objects['actions_sent']} of {objects['actions_recorded']}"
            f" creates, requests and releases sent ({objects['impatient']} before the"
            f" recorded owner, {len(objects['refused'])} refused)"
        )


def _speed(text: str) -> float | str:
    """--speed: a positive factor or ``max``."""
    try:
        factor = "max" if text == "max" else float(text)
    except ValueError:
        raise _fail("--speed takes a number or max") from None
    if factor != "max" and float(factor) <= 0:
        raise _fail("--speed must be positive")
    return factor


def _check_replay_args(
    offline: bool,
    url: str | None,
    window: tuple[float, float | None, str | None, bool],
    codec: str,
    object_patience: float = 1.0,
) -> None:
    """Refuse, in one line, replay options that cannot go together (exit 2)."""
    start, duration, _users, loop = window
    if offline == (url is not None):
        raise _fail("give either --url ws://HOST:PORT (live) or --offline")
    if offline and loop:
        raise _fail("--loop applies to a live replay (--url)")
    if start < 0 or (duration is not None and duration <= 0):
        raise _fail("--start must be 0 or more and --duration positive")
    if codec not in ("compact", "raw"):
        raise _fail(f"--codec must be compact or raw, not {codec!r}")
    if not object_patience >= 0:
        raise _fail("--object-patience must be 0 or more")


def _replay_passes(
    file: Path,
    url: str,
    factor: float | str,
    room: str | None,
    token: str | None,
    window: tuple[float, float | None, list[str] | None],
    loop: bool,
    options: tuple[str, float, str] = ("compact", 1.0, "none"),
) -> dict[str, Any]:
    """Replay live once, or (``--loop``) again and again until Ctrl-C; the last report."""
    from websockets.exceptions import InvalidURI, WebSocketException

    from posecast.client.replay import replay_live

    start, duration, users = window
    codec, patience, spawn = options
    passes = 0
    try:
        while True:
            with console.status(f"replaying {file.name} into {url} ..."):
                report: dict[str, Any] = _run_async(
                    replay_live(
                        file,
                        url,
                        factor,  # type: ignore[arg-type]
                        room,
                        token=token,
                        start_s=start,
                        duration_s=duration,
                        users=users,
                        codec=codec,
                        object_patience=patience,
                        spawn=spawn,
                    )
                )
            passes += 1
            if not loop:
                return report
            console.print(f"pass {passes} done; again (Ctrl-C stops)")
    except* ValueError as eg:
        raise _fail(f"{file}: {eg.exceptions[0]}") from None
    except* (OSError, InvalidURI, WebSocketException) as eg:
        raise _fail(connect_error(url, _first_leaf(eg))) from None


def export(
    file: Annotated[Path, typer.Argument(help="A session recording (.mcap).")],
    to: Annotated[str, typer.Option(help="csv, npz or foxglove.")],
    out: Annotated[Path | None, typer.Option(help="Output path (default beside FILE).")] = None,
    time: Annotated[
        str | None,
        typer.Option(
            "--time",
            help="Times as: relative (s since the recording started), wall (UNIX time, "
            "from the start time in the recording's header) or server (the server clock "
            "as recorded). [default: wall for foxglove, relative for csv and npz]",
            show_default=False,
        ),
    ] = None,
    z_up: Annotated[
        bool | None,
        typer.Option(
            "--z-up/--y-up",
            help="Turn the world z-up (+z up, +y forward: ROS and Foxglove), frame "
            "world_z_up; or keep the recording's y-up (OpenXR), frame world. "
            "[default: z-up for foxglove, y-up for csv and npz]",
            show_default=False,
        ),
    ] = None,
) -> None:
    """Export a recording as CSV, NPZ, or MCAP with Foxglove frame transforms.

    The files name their time base and world frame (streams.json, the NPZ index,
    the MCAP's posecast.export metadata).
    """
    from posecast.recorder.export import TIME_BASES
    from posecast.recorder.export import export as export_file

    if to not in ("csv", "npz", "foxglove"):
        raise _fail("--to takes csv, npz or foxglove")
    if time is not None and time not in TIME_BASES:
        raise _fail(f"--time takes relative, wall or server, not {time!r}")
    times = time or ("wall" if to == "foxglove" else "relative")
    turn = (to == "foxglove") if z_up is None else z_up
    _recording(file)
    stem = file.name.removesuffix(".part").removesuffix(".mcap")
    target = out or file.with_name(
        {"csv": f"{stem}-csv", "npz": f"{stem}.npz", "foxglove": f"{stem}-foxglove.mcap"}[to]
    )
    try:
        path = export_file(file, to, target, times=times, z_up=turn)  # type: ignore[arg-type]
    except (OSError, ValueError) as exc:
        raise _fail(f"{file}: {exc}") from None
    frame = "z-up (world_z_up)" if turn else "y-up (world)"
    console.print(f"wrote {path} ({times} times, {frame})")


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
    from posecast.recorder.analyze import analyze as run_analysis
    from posecast.recorder.analyze import format_analysis
    from posecast.scenarios.traces import TraceError

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
