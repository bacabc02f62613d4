"""Progress that shows on a terminal and when piped, and Ctrl-C that ends a run early.

On a terminal a long command draws rich's live progress bar. Piped (CI, ``| tee``,
a log file) a live display shows nothing at all, so :func:`progress` returns a
:class:`PlainProgress` instead: the same calls, printed as plain lines when a
stage starts, every ``every`` seconds while it runs, and when it ends.

:func:`stop_on_ctrl_c` turns the first SIGINT of a run into an event the run
watches (the bots end their sessions and report the time run); a second one
interrupts at once.
"""

from __future__ import annotations

import asyncio
import signal
import time
from collections.abc import Callable
from types import TracebackType
from typing import Any

from rich.console import Console
from rich.progress import Progress, ProgressColumn, TaskID

__all__ = ["PlainProgress", "progress", "stop_on_ctrl_c"]


class PlainProgress:
    """The part of :class:`rich.progress.Progress` the commands use, as plain lines.

    A line per task when it starts, then at most one every ``every`` seconds
    (``clock``: injectable for tests), and one when it completes:
    ``session: 5/20 s, 6 bots, 1234 poses relayed``.
    """

    def __init__(
        self,
        console: Console,
        *,
        unit: str = "",
        name: str = "",
        every: float = 5.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.console = console
        self.unit = f" {unit}" if unit else ""
        self.name = name
        self.every = every
        self.clock = clock
        self._tasks: dict[TaskID, dict[str, Any]] = {}

    def __enter__(self) -> PlainProgress:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        return None

    def add_task(self, description: str, total: float | None = 100.0, **fields: Any) -> TaskID:
        task = TaskID(len(self._tasks))
        self._tasks[task] = {
            "description": description,
            "total": total,
            "completed": 0.0,
            "printed": None,
            "done": False,
            **fields,
        }
        return task

    def update(self, task: TaskID, **changes: Any) -> None:
        state = self._tasks[task]
        state.update(changes)
        now = self.clock()
        total, completed = state["total"], state["completed"]
        finished = total is not None and completed >= total
        if state["done"] or not (
            state["printed"] is None or finished or now - state["printed"] >= self.every
        ):
            return
        state["printed"], state["done"] = now, finished
        amount = f"{completed:.0f}/{total:.0f}{self.unit}" if total else f"{completed:.0f}"
        if self.name:  # "session: 5/20 s, 6 bots, ..."
            head, tail = self.name, state["description"]
        else:  # "ideal: 3/40 ..."
            head, tail = state["description"].strip(), ""
        self.console.print(
            f"{head}: {amount}{', ' + tail if tail else ''}",
            markup=False,
            highlight=False,
            soft_wrap=True,
        )


def progress(
    console: Console, *columns: str | ProgressColumn, unit: str = "", name: str = ""
) -> Progress | PlainProgress:
    """A transient rich progress bar on a terminal, else :class:`PlainProgress`.

    ``name``: printed before each plain line, the task's description after the
    figures (without it, the description comes first); ``unit``: of the totals.
    """
    if console.is_terminal:
        return Progress(*columns, console=console, transient=True)
    return PlainProgress(console, unit=unit, name=name)


def stop_on_ctrl_c(console: Console | None = None) -> asyncio.Event:
    """An event the first Ctrl-C (SIGINT) sets, in the running loop; the next one
    raises KeyboardInterrupt as usual (the command then ends at once, exit 130)."""
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()

    def first() -> None:
        stop.set()
        loop.remove_signal_handler(signal.SIGINT)
        if console is not None:
            console.print(
                "interrupted: ending the run and reporting the time run (Ctrl-C again quits now)",
                markup=False,
                highlight=False,
            )

    loop.add_signal_handler(signal.SIGINT, first)
    return stop
