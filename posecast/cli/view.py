"""``posecast view``: the live 3D session viewer and the replay timeline in a browser."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from posecast.cli.common import (
    _fail,
    _first_leaf,
    _parse_methods,
    _run_async,
    connect_error,
    console,
)

__all__ = ["VIEW_METHODS", "view"]

VIEW_METHODS = "soa,dq-slerp,motor-hermite"


def _check_view_args(
    port: int, fps: float, rate: float, spread: float | None, duration: float | None
) -> None:
    if duration is not None and duration <= 0:
        raise _fail("--duration must be positive")
    if not 0 <= port <= 65535:
        raise _fail(f"--port {port} is not a TCP port (0-65535; 0: any free port)")
    if not fps > 0:
        raise _fail("--fps must be positive")
    if not rate > 0:
        raise _fail("--rate must be positive")
    if spread is not None and spread < 0:
        raise _fail("--spread must be 0 or more (metres)")


async def _serve(view: Any, run: Any, url_hint: str) -> None:
    console.print(f"viewer at [bold]{view.url}[/] ({url_hint}); Ctrl-C stops it")
    try:
        await run
    finally:
        view.close()


def view(
    file: Annotated[
        Path | None,
        typer.Argument(help="A session recording (.mcap) to replay; leave out with --url."),
    ] = None,
    url: Annotated[
        str | None, typer.Option(help="Watch this live server as a spectator (ws://HOST:PORT).")
    ] = None,
    room: Annotated[str, typer.Option(help="Live: the room to watch.")] = "lobby",
    interp_: Annotated[
        str, typer.Option("--interp", help="Interpolators drawn side by side (the first solid).")
    ] = VIEW_METHODS,
    host: Annotated[str, typer.Option(help="Serve the page on this address.")] = "127.0.0.1",
    port: Annotated[
        int, typer.Option(help="Serve the page on this port (0: any free one).")
    ] = 8080,
    rate: Annotated[
        float,
        typer.Option(help="Live: snapshot rate asked (Hz). Replay: keyframe rate of the ghosts."),
    ] = 10.0,
    fps: Annotated[float, typer.Option(help="Poses pushed to the page per second.")] = 60.0,
    spread: Annotated[
        float | None,
        typer.Option(
            help="Draw users this many metres apart along x (0: where they are). Default: "
            "where they are, but a user standing on another (a recording made without "
            "spawn points) is drawn 1.5 m over."
        ),
    ] = None,
    duration: Annotated[
        float | None, typer.Option(help="Stop after this many seconds (default: Ctrl-C).")
    ] = None,
    token_: Annotated[str | None, typer.Option("--token", help="Live: access token.")] = None,
) -> None:
    """Show a live room (--url) or a recording (FILE) in the browser, in 3D."""
    if (file is None) == (url is None):
        raise _fail("give either a recording FILE (replay) or --url ws://HOST:PORT (live)")
    if url is not None and not url.startswith(("ws://", "wss://")):
        raise _fail(f"--url {url!r} is not a websocket URL (ws://HOST:PORT)")
    methods = tuple(_parse_methods(interp_))
    _check_view_args(port, fps, rate, spread, duration)
    if file is not None:
        from posecast.cli.recordings import _recording
        from posecast.view.replay import ReplayView

        _recording(file)  # what is not a posecast recording is named as such, once
        try:
            rv = ReplayView(file, methods, rate=rate, host=host, port=port, fps=fps, spread=spread)
        except (OSError, ValueError) as exc:
            why = str(exc)
            raise _fail(why if why.startswith(str(file)) else f"{file}: {why}") from None
        rv.set_playing(True)
        _run_async(_serve(rv, rv.run(duration), f"replay of {file.name}"))
        return
    from posecast.view.live import LiveConfig, LiveView

    assert url is not None
    cfg = LiveConfig(
        url=url,
        room=room,
        methods=methods,
        host=host,
        port=port,
        rate=rate,
        fps=fps,
        token=token_,
        duration=duration,
        spread=spread,
    )

    async def live() -> None:
        lv = LiveView(cfg)
        await _serve(lv, lv.run(), f"room {room!r} of {url}")

    from websockets.exceptions import InvalidURI, WebSocketException

    try:
        _run_async(live())
    except* (OSError, TimeoutError, InvalidURI, WebSocketException) as eg:
        raise _fail(connect_error(url, _first_leaf(eg)).replace("connect to", "watch"), 1) from None
