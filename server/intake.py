"""What the adapter takes in for admission: queued connections, and the capacity's readings.

:class:`Intake` accepts every queued connection at each room tick, not one per
turn of the event loop; :func:`measure` gives the capacity (``server/capacity.py``)
the process's CPU time and the bytes unsent, twice a second.

uvloop (libuv) accepts one connection per turn of the loop (traced: one ``accept4``
each, never drained to ``EAGAIN``). A relay whose turns are long, many members on
a busy machine (60 ms a turn measured, a relay given a quarter of a core), then
accepts fewer connections a second than a join storm brings (16 against 37-50):
the kernel's accept queue grew to 1,150 and 369-1,197 of 2,000 joins got no answer
within 15 s, where each would have been refused in a millisecond. :class:`Intake`
holds a duplicate of each listening socket and, called from the tick timer, accepts
what is queued (up to ``BATCH`` a call) and hands each to the loop like any other
connection (``connect_accepted_socket``).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import socket
import ssl
import time
from collections.abc import Callable, Coroutine, Iterable
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    from posecast.server.core import RelayCore

__all__ = ["BATCH", "MEASURE_EVERY", "Intake", "measure"]

log = logging.getLogger("posecast.server")

#: Connections accepted at most per call (the rest wait for the next tick).
BATCH = 64
#: Seconds between the capacity's readings of CPU time and unsent bytes.
MEASURE_EVERY = 0.5


def measure(core: RelayCore, conns: Iterable[Buffered], now: float) -> float:
    """Give the capacity the process's CPU time, the bytes unsent over ``conns`` and the
    members at ``now``; when to measure next."""
    backlog = sum(conn.buffered() for conn in conns)
    members = sum(len(room.members) for room in core.rooms.values())
    core.capacity.sample(now, time.process_time(), backlog, members)
    return now + MEASURE_EVERY


class Buffered(Protocol):
    """A connection whose unsent bytes can be read."""

    def buffered(self) -> int: ...


class Intake:
    """The listening sockets of ``server``, drained on demand (:meth:`accept`)."""

    def __init__(
        self,
        server: asyncio.Server,
        factory: Callable[[], asyncio.Protocol],
        tls: ssl.SSLContext | None,
        spawn: Callable[[Coroutine[Any, Any, None], str], None],
    ) -> None:
        self._factory, self._tls, self._spawn = factory, tls, spawn
        # A duplicate descriptor: the listener stays the server's (closed with it).
        self._socks = [socket.socket(fileno=os.dup(s.fileno())) for s in server.sockets]
        for sock in self._socks:
            sock.setblocking(False)
        #: Connections accepted here (not by the loop's own accept).
        self.accepted = 0
        #: The hand-overs under way (a TLS handshake can take seconds): a stop cancels them.
        self._opening: set[asyncio.Task[Any]] = set()
        self._closed = False

    def accept(self) -> int:
        """Accept up to ``BATCH`` queued connections; how many."""
        n = 0
        for sock in self._socks:
            while n < BATCH:
                try:
                    conn, _ = sock.accept()
                except (BlockingIOError, InterruptedError):
                    break
                except OSError as exc:  # out of descriptors, say: the loop's accept retries
                    log.warning("accepting a connection failed: %s", exc)
                    return n
                conn.setblocking(False)
                n += 1
                self._spawn(self._open(conn), "accept")
        self.accepted += n
        return n

    async def _open(self, conn: socket.socket) -> None:
        task = asyncio.current_task()
        if self._closed or task is None:  # the relay stopped before it was handed over
            conn.close()
            return
        loop = asyncio.get_running_loop()
        self._opening.add(task)
        try:
            await loop.connect_accepted_socket(self._factory, conn, ssl=self._tls)
        except (OSError, TimeoutError) as exc:  # (ssl.SSLError is an OSError)
            log.debug("an accepted connection failed to open: %s", exc)
            conn.close()
        except Exception:  # a bug: this connection is lost, the relay goes on
            log.exception("opening an accepted connection failed")
            conn.close()
        finally:
            self._opening.discard(task)

    def close(self) -> None:
        """Stop accepting (each tick of a stop then accepts nothing, quietly); the
        hand-overs under way are cancelled (their sockets closed): a stop waits for
        no TLS handshake, and no connection is handed over after it."""
        self._closed = True
        socks, self._socks = self._socks, []
        for sock in socks:
            with contextlib.suppress(OSError):
                sock.close()
        for task in self._opening:
            task.cancel()
