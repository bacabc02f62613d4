"""What a relay's stop says when it takes longer than it should.

A stop closes every connection, each within its own bound (0.5 s for its queued
messages, then ``close_timeout`` for the closing handshake), then waits for the
server's tasks, which end as soon as they are cancelled. Neither wait should be
long; when one is, the log must say what is left, so that a stop which hangs can be
diagnosed from the log alone (a fresh-clone suite once hung for 10 minutes in a
cluster node's stop with nothing said: a task had lost its cancellation, see
``server/node.py``).

:func:`until_gone` waits for the connections' ends at most a bound, then names each
connection still open (peer, websocket state, close asked, bytes unsent) in one
warning; the caller aborts them. :func:`watch_tasks` names the tasks still running
(where each waits, and whether it was cancelled) once a bound has passed.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Collection
from typing import Protocol

__all__ = ["Open", "describe", "until_gone", "watch_tasks"]

log = logging.getLogger("posecast.server")

#: At most this many connections or tasks are named in one warning (the rest counted).
NAMED = 20


class Open(Protocol):
    """A connection as the stop sees it (``server/connection.py``)."""

    transport: asyncio.Transport
    is_open: bool
    close_request: tuple[int, str] | None

    def buffered(self) -> int: ...


def describe(conn: Open) -> str:
    """``conn`` in a few words: its peer, how far its websocket got, what it waits for."""
    transport = conn.transport
    if transport is None:  # (accepted, its connection_made not run yet)
        return "? (no transport yet)"
    peer = transport.get_extra_info("peername")
    where = f"{peer[0]}:{peer[1]}" if isinstance(peer, tuple) and len(peer) >= 2 else "?"
    state = getattr(getattr(conn, "protocol", None), "state", None)
    parts = [
        where,
        getattr(state, "name", "?"),
        "open" if conn.is_open else "no websocket yet",
    ]
    if conn.close_request is not None:
        parts.append(f"close {conn.close_request[0]} asked")
    if transport.is_closing():
        parts.append("transport closing")
    with contextlib.suppress(Exception):  # (a transport already torn down)
        parts.append(f"{conn.buffered()} B unsent")
    return " ".join(parts)


def _listed(items: list[str]) -> str:
    more = len(items) - NAMED
    return "; ".join(items[:NAMED]) + (f"; and {more} more" if more > 0 else "")


async def until_gone(conns: Collection[Open], gone: asyncio.Event, within: float) -> bool:
    """Wait until ``gone`` is set (the last of ``conns`` ended), at most ``within`` s;
    past it, name the connections still open in one warning. Whether all ended."""
    try:
        async with asyncio.timeout(within):
            await gone.wait()
        return True
    except TimeoutError:
        left = [describe(conn) for conn in list(conns)]
        log.warning(
            "stopping: %d connections did not end within %.1f s; aborted: %s",
            len(left), within, _listed(left),
        )  # fmt: skip
        return False


def _where(task: asyncio.Task[object]) -> str:
    frames = task.get_stack()
    cancelled = f" cancelled {task.cancelling()}x" if task.cancelling() else ""
    if not frames:
        return f"{task.get_name()}{cancelled}"
    frame = frames[-1]
    where = f"{frame.f_code.co_filename}:{frame.f_lineno} {frame.f_code.co_name}"
    return f"{task.get_name()}{cancelled} at {where}"


def _report(within: float, waiter: asyncio.Task[object] | None) -> None:
    tasks = [t for t in asyncio.all_tasks() if t is not waiter and not t.done()]
    log.warning(
        "stopping: still waiting after %.1f s; %d tasks running: %s",
        within, len(tasks), _listed(sorted(_where(t) for t in tasks)),
    )  # fmt: skip


def watch_tasks(within: float) -> asyncio.TimerHandle:
    """Name the tasks still running in ``within`` s (one warning), unless the returned
    timer is cancelled first (the stop ended): for a stop waiting on its tasks. A task
    said to be cancelled and still running lost its cancellation."""
    loop = asyncio.get_running_loop()
    return loop.call_later(within, _report, within, asyncio.current_task())
