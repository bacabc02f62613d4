"""The relay's capacity, from what it measures: may one more member come in? Sans I/O.

A relay past its capacity does not slow down evenly: every tick runs late, the
updates it reads have waited in its sockets, and each new member makes every
admitted member's session worse. :class:`Capacity` turns three measurements the
adapter (``server/app.py``) feeds it into one answer, :meth:`Capacity.refusal`:

==============  ===========================================================  ==========
signal          measured as                                                  budget
==============  ===========================================================  ==========
CPU             the relay process's CPU time (``time.process_time``) per     ``cpu``,
                second of wall time over the last complete window (1 s),     0.8 of a
                scaled to one more member: ``cpu * (members + 1) /           core
                members then`` (the mean over the window; members admitted
                since are counted: a ramp cannot overshoot by its joins)
tick lag        the share of room ticks more than ``lag`` late in the last   ``lag``,
                complete window (or the current one): over 1 % (the p99     25 ms
                is over budget) refuses, while the relay is loaded: it
                uses ``LAG_CPU_FLOOR`` of a core or holds
                ``LAG_MIN_MEMBERS`` (a near-idle relay lags because its
                machine is busy, and refusing would not cure that; a relay
                starved of CPU by other work uses little but lags with
                many members, and that counts)
backlog         bytes written but not yet taken by the kernel, summed over   ``backlog``,
                every connection, at the last sample                         32 MiB
growth          members admitted since the last CPU reading: at most half    with
                the members it measured, at least ``GROWTH_MIN`` (a slow     ``cpu``
                start: the readings must see new members before more come;
                on a machine shared with other work the relay gets less
                than the core its CPU budget assumes, and only its lag
                says so, a window late)
==============  ===========================================================  ==========

A join storm is not the members' load: the adapter times the work it does for
connections that are not members yet (:meth:`Capacity.join_work`: handshakes,
hellos, joins, refusals). Its CPU is kept out of the per-member scaling (it is
added as it is, not times ``(members + 1) / members``), and a tick late only by
the join work that ran after it was due does not count against the lag budget
(``ticks_late_for_joins``): one more member would not make it late, and a storm
of refused clients must not read as "full" by itself.

CPU and lag count from ``min_members`` members on (16): fewer cannot load a core by
themselves, so a busy reading then is someone else's. Over any budget, the join (or
the hello before it) is refused with the fatal
error ``server-full`` and close 1013 "try again later", its message saying when
to retry (:data:`RETRY_AFTER`), and ``error.retry_after`` too for a client whose
hello asked (``wants_retry_after``); members already in are untouched (a member resuming
its dropped connection is one of them). A budget of 0 turns its signal off.

:meth:`Capacity.overloaded` says the relay's ticks run late for the members' work
(over a tenth of a window's ticks over the lag budget): its rooms grew past what it
can carry, and ``server.rates`` offers its auto-rate subscribers lower rates (a
``rate`` notice each) instead of letting snapshots queue.

:meth:`Capacity.lateness` is how late the relay itself runs (the largest tick
lag of the recent windows): an update read that much later than it arrived is
not its sender's fault, so the capture-age limit is widened by it
(``server.core``).

Every measurement comes with its time, on the server's clock: tests drive this
with made-up readings, never with a real clock.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from posecast.protocol import ErrorCode, ErrorMessage, Hello, Join

if TYPE_CHECKING:
    from posecast.server.config import ServerConfig
    from posecast.server.peer import Peer
    from posecast.server.ports import Relay

__all__ = [
    "GROWTH",
    "GROWTH_MIN",
    "LAG_CPU_FLOOR",
    "LAG_MIN_MEMBERS",
    "PRESSURE_SHARE",
    "PRESSURE_TICKS",
    "RETRY_AFTER",
    "STALE_ERROR_INTERVAL",
    "Capacity",
    "CapacityBudget",
    "budget_of",
    "stale_error_due",
]

#: Seconds a refused client is told to wait before it tries this relay again.
RETRY_AFTER = 5.0
#: Tick lag counts against the budget only while the relay uses at least this share
#: of a core: an idle relay that ticks late is late because its machine is busy.
LAG_CPU_FLOOR = 0.2
#: ... or while it holds at least this many members (a starved relay uses little CPU).
LAG_MIN_MEMBERS = 16
#: Share of a window's ticks that may be later than the lag budget (1 %: the p99).
LAG_SHARE = 0.01
#: The relay runs too late for its rooms' rates (:meth:`Capacity.overloaded`: its
#: auto-rate subscribers are offered lower ones) when over this share of a window's
#: ticks are later than the lag budget ...
PRESSURE_SHARE = 0.1
#: ... out of at least this many ticks (one late tick of a few is a hiccup, not a load).
PRESSURE_TICKS = 10
#: Members admitted per CPU reading: at most this share of the members it measured ...
GROWTH = 0.5
#: ... and at least this many.
GROWTH_MIN = 16
#: A connection whose updates are stale gets one ``bad-pose`` error per this many seconds.
STALE_ERROR_INTERVAL = 1.0
#: A CPU reading older than this many windows is not used (no ticks ran to sample).
STALE_WINDOWS = 5
#: Spans of join work remembered (the most recent): enough for the joins between ticks.
SPANS = 256


@dataclass(frozen=True, slots=True)
class CapacityBudget:
    """What the relay may spend before it refuses members (0 turns a signal off)."""

    #: Share of one core the relay process may use (CPU seconds per second).
    cpu: float = 0.8
    #: Tick lag (s) that at most 1 % of a window's room ticks may exceed.
    lag: float = 0.025
    #: Bytes unsent, over every connection together.
    backlog: int = 32 << 20
    #: Seconds per measuring window.
    window: float = 1.0
    #: CPU and lag count from this many members on: fewer cannot load a core by
    #: themselves (a member costs microseconds a tick), so a busy reading then is
    #: someone else's (bots sharing the process, as in the demo and the tests).
    min_members: int = 16


def budget_of(config: ServerConfig) -> CapacityBudget:
    """The capacity budget of ``capacity_cpu``, ``capacity_lag``, ``capacity_backlog``
    (here, not on ServerConfig: the settings import nothing of the relay's parts)."""
    return CapacityBudget(
        config.capacity_cpu,
        config.capacity_lag,
        config.capacity_backlog,
        min_members=config.capacity_min_members,
    )


@dataclass
class _Window:
    """Room ticks of one window: how many, how many over the lag budget, the largest lag."""

    start: float
    ticks: int = 0
    late: int = 0
    worst: float = 0.0


@dataclass
class Capacity:
    """The relay's measurements and its budget; :meth:`refusal` decides."""

    budget: CapacityBudget = field(default_factory=CapacityBudget)
    #: CPU seconds per second over the last complete window, and the members it served
    #: (the mean of its first and last reading).
    cpu: float = 0.0
    cpu_members: int = 0
    #: Members at the last CPU reading (those admitted since are the growth).
    read_members: int = 0
    backlog: int = 0
    #: Joins refused, by error code (``posecast_joins_refused_total``).
    joins_refused: dict[str, int] = field(default_factory=dict)
    #: How late the relay runs (s): the largest tick lag of the recent windows.
    late: float = 0.0
    #: CPU seconds spent on connections that were not members yet (handshakes, hellos,
    #: joins, refusals): a join storm's cost, kept apart from the members' (:meth:`join_work`).
    join_cpu: float = 0.0
    #: The share of a core the join work used over the last CPU window.
    join_share: float = 0.0
    #: Ticks late over the lag budget, and those of them on time but for the join work
    #: that ran since they were due (``posecast_ticks_late_total``).
    ticks_late: int = 0
    ticks_late_for_joins: int = 0
    #: (start, end) of the join work of the recent past, on the server's clock.
    _spans: deque[tuple[float, float]] = field(default_factory=lambda: deque(maxlen=SPANS))
    _sampled: float | None = None
    _cpu_at: tuple[float, float, int, float] | None = None
    _current: _Window | None = None
    _previous: _Window | None = None

    # -- measurements (the adapter) ----------------------------------------------------

    def sample(self, now: float, cpu_seconds: float, backlog: int, members: int) -> None:
        """The process's CPU time so far, the bytes unsent and the members, at ``now``.

        Called often (each tick is fine): a CPU figure is taken once a window has passed.
        """
        self.backlog = backlog
        if self._cpu_at is None:
            self._cpu_at = (now, cpu_seconds, members, self.join_cpu)
            return
        t0, c0, m0, j0 = self._cpu_at
        if now - t0 >= self.budget.window:
            self.cpu = max(0.0, cpu_seconds - c0) / (now - t0)
            self.join_share = min(self.cpu, max(0.0, self.join_cpu - j0) / (now - t0))
            # The members the window's CPU served: a ramp's members joined during it.
            self.cpu_members = round((m0 + members) / 2)
            self.read_members = members
            self._cpu_at = (now, cpu_seconds, members, self.join_cpu)
            self._sampled = now

    def join_work(self, start: float, end: float, cpu: float) -> None:
        """The relay worked for a connection that was not a member yet (its handshake,
        hello, join or refusal) from ``start`` to ``end``, for ``cpu`` CPU seconds."""
        self.join_cpu += cpu
        self._spans.append((start, end))

    def _joins_since(self, due: float) -> float:
        """Seconds of join work that ran after ``due`` (what delayed a tick due then)."""
        total = 0.0
        for start, end in reversed(self._spans):  # (in the order they ended)
            if end <= due:
                break
            total += end - max(start, due)
        return total

    def tick_lag(self, now: float, lag: float) -> None:
        """One room tick ran ``lag`` seconds after it was due.

        A tick late only because of the join work that ran since it was due is late
        for the join storm, not for its members: it does not count against the lag
        budget (one more member would not make it late), only in ``ticks_late``."""
        w = self._roll(now)
        w.ticks += 1
        if lag > self.budget.lag:
            self.ticks_late += 1
            if lag - self._joins_since(now - lag) > self.budget.lag:
                w.late += 1
            else:
                self.ticks_late_for_joins += 1
        if lag > w.worst:
            w.worst = lag
            self.late = max(self.late, lag)

    def _roll(self, now: float) -> _Window:
        w = self._current
        if w is None or now - w.start >= self.budget.window:
            # A gap of more than one window leaves no previous window: it was idle.
            gap = w is None or now - w.start >= 2 * self.budget.window
            self._previous = None if gap else w
            w = self._current = _Window(now)
            self.late = 0.0 if self._previous is None else self._previous.worst
        return w

    # -- answers -------------------------------------------------------------------------

    def _windows(self, now: float) -> list[_Window]:
        """The windows that are recent at ``now`` (the current one and the one before)."""
        w = self._current
        if w is None or now - w.start >= 2 * self.budget.window:
            return []
        if now - w.start >= self.budget.window:
            return [w]
        return [x for x in (self._previous, w) if x is not None]

    def lateness(self, now: float) -> float:
        """How late the relay runs at ``now`` (s): the largest tick lag of the recent
        windows (:attr:`late` is the same as of the last tick, for the hot path)."""
        return max((w.worst for w in self._windows(now)), default=0.0)

    def overloaded(self, now: float) -> bool:
        """Whether the relay runs too late to carry its rooms at their rates at ``now``:
        over :data:`PRESSURE_SHARE` of the ticks of a recent window (of at least
        :data:`PRESSURE_TICKS`) were later than the lag budget for the members' work
        (a join storm's lateness does not count), while it is loaded as for the lag
        budget (:meth:`usage`: with its members at the last reading). ``server.rates``
        then offers its auto-rate subscribers lower rates. Off with the lag budget."""
        if self.budget.lag <= 0 or not self._loaded(self.read_members, now):
            return False  # (a near-idle relay is late for its machine: lower rates would not help)
        return any(
            w.ticks >= PRESSURE_TICKS and w.late > PRESSURE_SHARE * w.ticks
            for w in self._windows(now)
        )

    def _loaded(self, members: int, now: float) -> bool:
        """Whether the relay's lag is its members' doing: it holds ``min_members`` and uses
        ``LAG_CPU_FLOOR`` of a core (its last reading) or holds ``LAG_MIN_MEMBERS``."""
        b = self.budget
        if members < b.min_members:
            return False
        fresh = self._sampled is not None and now - self._sampled <= STALE_WINDOWS * b.window
        return (fresh and self.cpu >= LAG_CPU_FLOOR) or members >= LAG_MIN_MEMBERS

    def usage(self, members: int, now: float) -> dict[str, float]:
        """Each signal as a share of its budget with one more member (over 1: refused)."""
        b = self.budget
        out = {"cpu": 0.0, "lag": 0.0, "backlog": 0.0, "growth": 0.0}
        fresh = self._sampled is not None and now - self._sampled <= STALE_WINDOWS * b.window
        few = members < b.min_members
        if b.cpu > 0 and fresh and self.cpu_members > 0 and not few:
            # The members' CPU scales with one more member; the join work does not.
            steady = self.cpu - self.join_share
            out["cpu"] = (steady * (members + 1) / self.cpu_members + self.join_share) / b.cpu
        if b.cpu > 0 and fresh:  # (no reading yet: nothing to grow from)
            since = self.read_members
            out["growth"] = (members + 1 - since) / max(GROWTH_MIN, GROWTH * since)
        if b.lag > 0 and self._loaded(members, now):
            share = max((w.late / w.ticks for w in self._windows(now) if w.ticks), default=0.0)
            out["lag"] = share / LAG_SHARE
        if b.backlog > 0:
            out["backlog"] = self.backlog / b.backlog
        return out

    def refusal(self, members: int, now: float) -> str | None:
        """Why one more member (beside ``members``) is refused now; None: it fits."""
        use = self.usage(members, now)
        b = self.budget
        if use["cpu"] > 1.0:
            return (
                f"the relay is full: {members + 1} members would use {use['cpu'] * b.cpu:.2f}"
                f" of a core, over its budget of {b.cpu:g}"
            )
        if use["lag"] > 1.0:
            return f"the relay is full: over 1 % of its ticks run over {1e3 * b.lag:g} ms late"
        if use["growth"] > 1.0:
            return f"the relay is full for now: {members} members, measuring the last ones"
        if use["backlog"] > 1.0:
            return f"the relay is full: {self.backlog >> 20} MiB unsent, over {b.backlog >> 20} MiB"
        return None

    def count(self, code: ErrorCode) -> None:
        """One join refused with ``code``."""
        self.joins_refused[code] = self.joins_refused.get(code, 0) + 1

    def shed(self, core: Relay, peer: Peer, event: Hello | Join, now: float) -> bool:
        """Refuse ``event`` with ``server-full`` (close 1013) if one more member is over the
        budget; True if it was refused. A hello resuming a member (and its join), or one a
        cluster node forwarded (that node welcomed it), is never refused here; a forwarded
        join is: this node owns the room and would carry the member's fan-out."""
        if isinstance(event, Hello):
            peer.wants_retry_after = event.wants_retry_after
            if event.resume or peer.preset_user is not None:
                return False
        if isinstance(event, Join) and peer.parked is not None:
            return False  # (its parked member is re-bound, unless the join asks otherwise)
        members = sum(len(room.members) for room in core.rooms.values())
        why = self.refusal(members, now)
        if why is None:
            return False
        self.count(ErrorCode.SERVER_FULL)
        what = "hello" if isinstance(event, Hello) else "join"
        why += f"; retry in {RETRY_AFTER:g} s"
        retry = RETRY_AFTER if peer.wants_retry_after else None  # (a field only if asked)
        error = ErrorMessage.from_code(
            ErrorCode.SERVER_FULL, why, in_reply_to=what, retry_after=retry
        )
        core.send(peer, error)
        core.close_peer(peer, ErrorCode.SERVER_FULL.close_code or 1013, f"try again later: {why}")
        return True


def stale_error_due(peer: Peer, now: float) -> bool:
    """Whether ``peer``'s stale update is answered with an error (one a second at most:
    each error is work for a relay that may be late already); True notes it sent."""
    if now - peer.stale_error_at < STALE_ERROR_INTERVAL:
        return False
    peer.stale_error_at = now
    return True
