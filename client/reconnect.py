"""How a client's session ends, and whether it reconnects: a state machine, sans I/O.

:class:`Reconnect` holds the client's rules for a connection that ended; the
asyncio adapter (:mod:`client.bot`) reports what happened with the time it
happened (nothing here reads a clock) and carries out what it says:

=============  ==========================================  ===================
state          event (adapter calls)                       next state
=============  ==========================================  ===================
connected      ``ended(code, ...)`` and it reconnects:     reconnecting
               a drop (no close frame) with a resume
               token or other relays; 1012 (a cluster
               node asks its clients back); 1001 with
               other relays
connected      ``ended(...)`` otherwise                    ended (closed/lost)
reconnecting   ``refused(i)``: the join on relay ``i``     reconnecting (next
               failed; more than one relay                 relay), else ended
reconnecting   ``reconnected(i, resumed, now)``            connected
reconnecting   ``gave_up(after)``: the window closed       ended (as dropped)
=============  ==========================================  ===================

The window: a reconnecting client tries until ``min(stop, dropped + window)``
(server clock), to the relay it was on and then the others in order, cycling.

Keepalive: the client pings its connection every :data:`KEEPALIVE_INTERVAL` s and
drops it when no pong came within :data:`KEEPALIVE_TIMEOUT` s, as the relay does,
and closes it without waiting over :data:`CLOSE_TIMEOUT` s for a close frame that
cannot come, so a silently dead path (socket open, bytes dropped) is noticed
within 7.5 s, inside the relay's 10 s resume window, and the client resumes.

:class:`SessionEnd` says how a session ended. ``complete`` means: the session ran
its whole duration (resumes along the way allowed) and showed fresh poses for at
least half of it; one that ran its duration but held every remote stream (no
fresh pose) for more than :data:`STALE_SHARE` of its render time (counting
stretches of over 1 s: ``client.log.STALE_STRETCH``) ended ``stalled``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Literal

__all__ = [
    "CLOSE_TIMEOUT",
    "GRACEFUL_CLOSE_CODES",
    "KEEPALIVE_INTERVAL",
    "KEEPALIVE_TIMEOUT",
    "STALE_SHARE",
    "Reconnect",
    "SessionEnd",
]

#: Close codes of a server that ended the session on purpose (normal, going away).
GRACEFUL_CLOSE_CODES = frozenset({1000, 1001})
#: Client keepalive: a ping this often (s), the connection dropped when its pong is
#: this late (s). The relay's defaults; their sum is under the resume window (10 s).
KEEPALIVE_INTERVAL = 2.5
KEEPALIVE_TIMEOUT = 2.5
#: How long a closing connection waits for the other side's close frame (s): after a
#: keepalive timeout the path is dead and none will come, so the drop is known
#: ``KEEPALIVE_INTERVAL + KEEPALIVE_TIMEOUT + CLOSE_TIMEOUT`` (7.5 s) after the last
#: byte at most, inside the resume window.
CLOSE_TIMEOUT = 2.5
#: A session that ran its duration is ``stalled`` when over this share of its render
#: time showed no fresh pose of anyone (every remote stream held past its newest).
STALE_SHARE = 0.5


@dataclass(frozen=True)
class SessionEnd:
    """How a bot's session ended, and after how many seconds of it.

    ``kind``: ``complete`` (ran its duration, fed), ``stalled`` (ran its duration but
    over :data:`STALE_SHARE` of it without fresh poses: ``stale_s``), ``closed`` (the
    server sent a close frame: ``code`` and ``reason`` are its), ``lost`` (no close
    frame: the connection broke) or ``interrupted`` (its runner stopped it early,
    e.g. on Ctrl-C: ``run_bot(stop=...)``). ``after_s`` counts from the start of the
    session (clock synced, before joining) on the bot's clock.
    """

    kind: Literal["complete", "stalled", "closed", "lost", "interrupted"] = "complete"
    after_s: float = 0.0
    code: int | None = None
    reason: str = ""
    #: Render time (s) with no fresh pose of anyone: every remote stream held.
    stale_s: float = 0.0

    @property
    def graceful(self) -> bool:
        """Ran its duration (or as long as its runner wanted), or the server ended it
        on purpose (1000/1001)."""
        return self.kind in ("complete", "interrupted") or (
            self.kind == "closed" and self.code in GRACEFUL_CLOSE_CODES
        )

    def describe(self) -> str:
        """``complete``, ``server closed: going away (1001) after 2.0 s``,
        ``connection lost after 12.3 s``."""
        if self.kind == "complete":
            return "complete"
        if self.kind == "stalled":
            return f"stalled: no fresh poses for {self.stale_s:.1f} s of {self.after_s:.1f} s"
        if self.kind == "closed":
            why = self.reason or "no reason given"
            return f"server closed: {why} ({self.code}) after {self.after_s:.1f} s"
        if self.kind == "interrupted":
            return f"interrupted after {self.after_s:.1f} s"
        return f"connection lost after {self.after_s:.1f} s"


def ran_to_the_end(after: float, stale: float) -> SessionEnd:
    """The ending of a session that ran its duration: ``complete``, or ``stalled``
    when over :data:`STALE_SHARE` of its ``after`` seconds showed nothing fresh."""
    kind: Literal["complete", "stalled"] = "stalled" if stale > STALE_SHARE * after else "complete"
    return SessionEnd(kind, after, stale_s=stale)


@dataclass
class Reconnect:
    """A client's reconnect policy (see the module's table). ``relays`` in the order
    it tries them; ``enabled``: it asked the relay to hold its place
    (``BotConfig.resume``); ``window``: how long it tries (s)."""

    relays: tuple[str, ...]
    enabled: bool = True
    window: float = 10.0
    #: The relay it is on (index in ``relays``).
    relay: int = 0
    state: Literal["connected", "reconnecting", "ended"] = "connected"
    #: While reconnecting: until when (server clock).
    deadline: float = float("inf")
    #: The close that made it reconnect (None: a drop): its ending if that fails.
    dropped: SessionEnd | None = None
    #: When it resumed / rejoined as a new member (the adapter's clock).
    resumed_at: list[float] = field(default_factory=list)
    rejoined_at: list[float] = field(default_factory=list)
    #: How it ended (set once it is ``ended``).
    ending: SessionEnd | None = None

    def reconnects(self, code: int | None, *, joined: bool, resume_token: bool) -> bool:
        """Whether a joined session goes on after its connection ended: a drop (``code``
        None) with a resume token or other relays; a relay going away (1001) with others;
        a cluster node that asks its clients to reconnect (1012, its room's owner died)."""
        if not self.enabled or not joined:
            return False
        several = len(self.relays) > 1
        if code is None:
            return several or resume_token
        return code == 1012 or (several and code == 1001)

    def ended(
        self,
        code: int | None,
        reason: str,
        after: float,
        *,
        joined: bool,
        resume_token: bool,
    ) -> bool:
        """The connection ended (``code``: its close frame's, None without one) ``after``
        seconds into the session. True: reconnect (call :meth:`start`); else the
        session is over (``ending``). A second report of the same end is ignored."""
        if self.state != "connected":
            return self.state == "reconnecting"
        if self.reconnects(code, joined=joined, resume_token=resume_token):
            self.state = "reconnecting"
            self.dropped = None if code is None else SessionEnd("closed", 0, code, reason)
            return True
        self.finish(
            SessionEnd("lost", after) if code is None else SessionEnd("closed", after, code, reason)
        )
        return False

    def start(self, now: float, stop: float) -> float:
        """Reconnecting from server time ``now``; returns the deadline (server clock)."""
        self.deadline = min(stop, now + self.window)
        return self.deadline

    def refused(self, i: int) -> bool:
        """The relay ``i`` answered but refused the join (or went away meanwhile):
        True to try the next one; False with one relay only (the session ends)."""
        if len(self.relays) == 1:
            return False
        self.relay = (i + 1) % len(self.relays)
        return True

    def reconnected(self, i: int, resumed: bool, now: float) -> None:
        """Back on relay ``i`` at ``now`` (the adapter's clock): resumed (the same user
        and streams) or rejoined as a new member."""
        self.relay, self.state = i, "connected"
        (self.resumed_at if resumed else self.rejoined_at).append(now)

    def gave_up(self, after: float) -> SessionEnd:
        """The window closed (or its one relay refused): the session ends as it dropped."""
        self.finish(replace(self.dropped or SessionEnd("lost"), after_s=after))
        assert self.ending is not None
        return self.ending

    def finish(self, ending: SessionEnd) -> None:
        """The session is over, as ``ending`` says (the first ending wins)."""
        if self.ending is None:
            self.ending = ending
        self.state = "ended"
