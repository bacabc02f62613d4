"""What every ``posecast`` command shares: the app, its error handling, consoles, parsers.

The commands themselves live beside this module by group and are registered,
in the order ``posecast --help`` lists them, in :mod:`posecast.cli`.
"""

from __future__ import annotations

import errno
import importlib
import sys
from difflib import get_close_matches
from pathlib import Path
from typing import Annotated, Any

import typer
from rich import box
from rich.console import Console
from rich.markup import escape
from rich.table import Table
from typer.core import TyperGroup


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

    def main(self, *args: Any, **kwargs: Any) -> Any:
        """Run the command line; a mistake the parser finds (an unknown command or
        option, a bad or missing value) is one line and exit 2, not a usage box."""
        if not kwargs.get("standalone_mode", True):
            return super().main(*args, **kwargs)
        kwargs["standalone_mode"] = False
        click = _click_exceptions()
        try:
            result = super().main(*args, **kwargs)
        except click.ClickException as exc:
            if type(exc).__name__ == "NoArgsIsHelpError":  # the help, already shown by rich
                if message := exc.format_message().strip():
                    print(message, file=sys.stderr)
                sys.exit(exc.exit_code)
            sys.exit(_fail(_parser_message(exc), exc.exit_code).exit_code)
        except typer.Abort:
            sys.exit(_fail("aborted", 1).exit_code)
        sys.exit(result if isinstance(result, int) else 0)


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


def version_lines() -> list[str]:
    """What ``posecast --version`` prints: the package, the protocol it speaks, the codec
    path and the render kernels' (:mod:`interp.accel`).

    The codec path is ``protocol.codec.IMPLEMENTATION`` when the codec module
    sets it (a compiled accelerator names itself there), else the pure-Python one.
    """
    from importlib.metadata import PackageNotFoundError, version

    from posecast.protocol import PROTOCOL_VERSION
    from posecast.protocol import codec as codec_module

    try:
        package = version("posecast")
    except PackageNotFoundError:  # run from a source tree that is not installed
        package = "unknown (not installed)"
    from posecast.interp import accel as render_accel

    path = getattr(codec_module, "IMPLEMENTATION", "pure Python (numpy)")
    return [
        f"posecast {package}",
        f"protocol version {PROTOCOL_VERSION}",
        f"codec: {path}",
        f"render kernels: {render_accel.IMPLEMENTATION}",
        f"python {sys.version.split()[0]}",
    ]


def _show_version(value: bool) -> None:
    if value:
        print("\n".join(version_lines()))
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[
        bool,
        typer.Option(
            "--version",
            is_eager=True,
            callback=_show_version,
            help="Print the package and protocol versions and the codec path, and exit.",
        ),
    ] = False,
) -> None:
    """Networked VR pose streaming: relay server, headless bots, pose interpolators
    and a QoE bench."""


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


def _click_exceptions() -> Any:
    """The click exceptions typer raises (typer >= 0.23 vendors click as typer._click)."""
    try:
        return importlib.import_module("typer._click.exceptions")
    except ImportError:
        return importlib.import_module("click.exceptions")


def _parser_message(exc: Any) -> str:
    """One line for a mistake the parser found, with a "did you mean" where one is close."""
    ctx = getattr(exc, "ctx", None)
    where = "posecast" if ctx is None else ctx.command_path
    see = f"see `{where} --help`"
    name = type(exc).__name__
    if name == "NoSuchOption":
        option = exc.option_name
        known = _option_names(ctx)
        close = list(exc.possibilities or ()) or get_close_matches(option, known, n=3)
        close = [c for c in close if c in known] or close
        if close:
            return f"{where} has no option {option}; did you mean {' or '.join(close)}?"
        return f"{where} has no option {option}; {see}"
    text = " ".join(exc.format_message().split())
    if text.startswith("No such command"):
        text = text.split(". Did you mean")[0].rstrip(".")
        typed = text.split("'")[1] if text.count("'") >= 2 else ""
        commands = sorted(getattr(ctx.command, "commands", {}) or {}) if ctx else []
        close = get_close_matches(typed, commands, n=3)
        if close:
            return f"{where} has no command {typed!r}; did you mean {' or '.join(close)}?"
        return f"{where} has no command {typed!r}; commands: {', '.join(commands)}"
    text = text.replace("Value error, ", "").replace("Input should be", "it should be")
    text = text[:1].lower() + text[1:]
    return f"{where}: {text.rstrip('.')}; {see}"


def _option_names(ctx: Any) -> list[str]:
    """Every long and short option name of the command of ``ctx``."""
    if ctx is None:
        return []
    names: list[str] = []
    for param in ctx.command.params:
        names.extend(
            o for o in (*param.opts, *getattr(param, "secondary_opts", ())) if o[:1] == "-"
        )
    return names


# Refusals that answer what the user typed (a rate, a room name): usage mistakes, exit 2.
_USAGE_CODES = ("bad-rate", "bad-room")

_PATH_ERRORS = (FileNotFoundError, FileExistsError, IsADirectoryError, NotADirectoryError)


def _user_error(exc: BaseException) -> tuple[str, int] | None:
    """The one line and exit code for a user-facing error; None for anything else.

    A :class:`PosecastError` that is also a ``ValueError`` (a bad file, tier, trace,
    token...) or a refused rate or room name is a usage mistake (2); any other one failed at run
    time (1). An ``OSError`` naming a path that is missing, present or of the
    wrong kind is a usage mistake (2), any other (a taken port, a full disk) 1. An
    exception group counts if all its exceptions do; the first one is reported.
    """
    if isinstance(exc, BaseExceptionGroup):
        found = [_user_error(e) for e in exc.exceptions]
        if not found or any(f is None for f in found):
            return None
        return found[0]
    from posecast.protocol.errors import PosecastError

    if isinstance(exc, PosecastError):
        from posecast.client.connection import JoinRefused

        if isinstance(exc, JoinRefused):
            message = f"join refused ({exc.code}): {exc.message}"
        else:
            message = str(exc)
        usage = isinstance(exc, ValueError) or getattr(exc, "code", None) in _USAGE_CODES
        return message, 2 if usage else 1
    if isinstance(exc, OSError) and exc.errno != errno.EPIPE:
        return _os_message(exc), 2 if isinstance(exc, _PATH_ERRORS) else 1
    return None


def connect_error(url: str, exc: BaseException) -> str:
    """``cannot connect to URL: why``, with a reason even when ``exc`` has no text.

    A ``wss://`` handshake against a plain ``ws://`` server ends in a reset (or an
    SSL record error) that says nothing: the line names the likely cause.
    """
    import ssl

    why = str(exc).strip()
    tls_failed = isinstance(exc, ssl.SSLError | ConnectionResetError | EOFError) or (
        "record layer" in why or "WRONG_VERSION_NUMBER" in why
    )
    if url.startswith("wss://") and tls_failed:
        plain_url = "ws://" + url.removeprefix("wss://")
        why = (
            "the TLS handshake failed"
            + (f" ({why})" if why else "")
            + f"; is it a plain server? Try {plain_url}"
        )
    elif not why:
        reasons: dict[type[BaseException], str] = {
            ConnectionResetError: "the server reset the connection",
            ConnectionRefusedError: "connection refused",
            TimeoutError: "timed out",
        }
        why = reasons.get(type(exc), type(exc).__name__)
    return f"cannot connect to {url}: {why}"


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
    from posecast import interp

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


# Name, statistic, unit: three short header lines keep the table inside 80 columns.
_QOE_COLUMNS = (
    "pos\np50\nmm",
    "pos\np95\nmm",
    "rot\np50\ndeg",
    "rot\np95\ndeg",
    "tip\np50\nmm",
    "tip\np95\nmm",
    "stall\n\n%",
)


def small_table(title: str) -> Table:
    """A table without vertical rules, one space between columns: fits 80 columns."""
    return Table(
        title=title, title_justify="left", box=box.SIMPLE_HEAD, padding=(0, 0), show_edge=False
    )


def plain(text: str) -> None:
    """Print ``text`` as it is (no markup, no highlighting), wrapped to the terminal."""
    console.print(text, markup=False, highlight=False)


def _qoe_table(title: str, keys: tuple[str, ...]) -> Table:
    """A table with ``keys`` columns then the DESIGN.md QoE columns."""
    table = small_table(title)
    for col in keys:
        table.add_column(col, no_wrap=True)
    for col in _QOE_COLUMNS:
        table.add_column(col, justify="right", no_wrap=True, min_width=6)
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


def _tier(name: str | None, path: Path | None) -> Any:
    """The tier called ``name`` (None: no link emulation) from the built-in tiers and
    ``path``; a tiers file is read, and checked, even without a name."""
    from posecast.scenarios.network import load_tiers

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
