"""What every ``posecast`` command shares: the app, its error handling, consoles, parsers.

The commands themselves live beside this module by group and are registered,
in the order ``posecast --help`` lists them, in :mod:`posecast.cli`.
"""

from __future__ import annotations

import errno
import sys
from pathlib import Path
from typing import Any

import typer
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
    from posecast.protocol.errors import PosecastError

    if isinstance(exc, PosecastError):
        from posecast.client.connection import JoinRefused

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
