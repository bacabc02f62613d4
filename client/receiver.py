"""The asyncio receive side of a client: a connection's events into a :class:`ClientCore`.

:class:`Receiver` is the thin adapter the bot and the viewer's spectator share:
it syncs the clock (pings, lowest round trip kept), hands every received event
with its arrival time to the core (and to listeners: the bot's scene actor, a
test's spy), pings now and then, and reports a connection's end to the
reconnect policy (:class:`client.reconnect.Reconnect`), which decides. It holds
no rule of its own.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

from websockets.exceptions import ConnectionClosed

from posecast.client.connection import ClientConnection
from posecast.client.core import ClientCore
from posecast.client.reconnect import Reconnect
from posecast.protocol import LocalProtocolError, Ping, Pong

__all__ = ["Listener", "Receiver"]

#: Called with every received event, its arrival (caller's clock) and size.
Listener = Callable[[object, float, int], None]


class Receiver:
    """One client's receive side over ``core`` (see the module docstring)."""

    def __init__(
        self,
        core: ClientCore,
        policy: Reconnect,
        clock: Callable[[], float] = time.monotonic,
        *,
        ping_interval: float = 1.0,
    ) -> None:
        self.core = core
        self.policy = policy
        self.clock = clock
        self.ping_interval = ping_interval
        #: The connection it is on (a new one after a reconnect).
        self.conn: ClientConnection | None = None
        #: Set when the connection ended and the policy says reconnect.
        self.lost = asyncio.Event()
        #: The caller's clock when the session started (after the clock sync).
        self.started_local = 0.0
        self.ping_seq = 0
        self._listeners: list[Listener] = []

    def listen(self, listener: Listener) -> None:
        """Call ``listener`` with every event received, after the core took it."""
        self._listeners.append(listener)

    def attach(self, conn: ClientConnection) -> None:
        """Receive on ``conn`` from now on (its user id and the room's objects)."""
        self.conn = conn
        if conn.welcome is not None:
            self.core.me = conn.user
        self.core.objects = conn.session.objects
        for ev in conn.early_peers:
            self.core.peer_joined(ev)

    def on_event(self, event: object, arrival: float, size: int) -> None:
        self.core.receive(event, arrival, size)
        for listener in self._listeners:
            listener(event, arrival, size)

    def after(self) -> float:
        """Seconds since the session started (caller's clock)."""
        return max(0.0, self.clock() - self.started_local)

    def closed(self, exc: ConnectionClosed) -> None:
        """The connection ended: the policy says whether to reconnect (``lost`` set)."""
        conn, rcvd = self.conn, exc.rcvd
        joined = conn is not None and conn.welcome is not None and conn.joined is not None
        token = conn is not None and conn.welcome is not None and conn.welcome.resume is not None
        code, reason = (None, "") if rcvd is None else (rcvd.code, rcvd.reason)
        if self.policy.ended(code, reason, self.after(), joined=joined, resume_token=token):
            self.lost.set()

    async def sync(self, conn: ClientConnection, n: int) -> None:
        """``n`` pings, each waiting for its pong (events meanwhile go to the core)."""
        for _ in range(n):
            self.ping_seq += 1
            await conn.send(Ping(seq=self.ping_seq, time=self.clock()))
            while True:
                rec = await conn.recv()
                self.on_event(rec.event, rec.arrival, rec.size)
                if isinstance(rec.event, Pong):
                    break

    async def receive(self, conn: ClientConnection) -> None:
        """Every event of ``conn`` into the core, until the connection ends."""
        try:
            while True:
                rec = await conn.recv()
                self.on_event(rec.event, rec.arrival, rec.size)
        except ConnectionClosed as exc:
            self.closed(exc)

    async def ping(self, conn: ClientConnection, stop: float) -> None:
        """A clock ping every ``ping_interval`` s until server time ``stop``."""
        try:
            while self.core.server_time(self.clock()) < stop:
                await asyncio.sleep(self.ping_interval)
                self.ping_seq += 1
                await conn.send(Ping(seq=self.ping_seq, time=self.clock()))
        except ConnectionClosed as exc:
            self.closed(exc)
        except LocalProtocolError:
            if not conn.session.closed:
                raise
