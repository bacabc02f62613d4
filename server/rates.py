"""Link-aware snapshot rates (``join.rate = "auto"``): each subscriber's rate from its link.

A subscriber that joins with ``rate="auto"`` (and optionally ``max_rate``) lets the
relay choose its snapshot rate within ``[min_rate, max_rate]``. A :class:`LinkRate`
per such subscriber watches what its link takes and chooses the rate that fits,
sans I/O: at each decision the relay hands it the subscriber's cumulative egress
counters (:class:`Egress`) and the time, and it answers with a new rate or None.

What it watches (all of it the relay's own view of its egress, no client report):

- **skips**: member ticks whose snapshot did not go, because the previous one still
  waited unsent (latest wins), the socket's write buffer was over its congestion
  bound, or an emulated link's cap (``serve --link``) refused it;
- **drained bytes**: what left the relay (written to the socket less what still
  waits in its buffer; on an emulated link, what got through its cap);
- **backlog**: the bytes waiting in the socket's write buffer now.

The rule, evaluated once per ``window`` (0.5 s):

- *at the edge* (one skip, none in the ``isolated_s`` (3 s) before it, no backlog,
  no step up on trial): the link carries about this rate; it **stays**, and the
  next rate up counts as the ceiling (no step up while such skips keep coming).
  A rate a little above the cap skips one snapshot every several seconds, which
  costs less than a whole Hz less (the mediocre tier's 20 Hz);
- *congested* (more skips, or a backlog of more than ``backlog_frames``
  snapshots): **down fast**, at once, to the rate the measured drain carries
  (``headroom x drained bytes/s / bytes per snapshot``), at least 1 Hz below the
  rate that failed (``down_factor`` below it before any snapshot got through);
  that rate is remembered as the link's *ceiling*;
- *the relay late* (``relay_late``: the relay's own ticks run late for its
  members' work, ``server.capacity.Capacity.overloaded``): the room grew past what
  the relay can carry; **down fast** as if congested, whatever the link did (the
  relay skips grid points already: the drain it measures is what it managed);
- *clear* for ``up_after`` (1 s) since the last congestion and ``up_every`` (0.5 s)
  since the last change: **up slowly**, by ``up_step`` (25 %) of the rate (at least 1 Hz),
  but not to the ceiling until the ceiling is ``ceiling_hold`` (10 s) old: the
  probe of a known limit is rare, so the rate does not oscillate around it. A step
  up that fails at once (within ``2 up_every``) goes back to the rate before it,
  and then no step up for ``ceiling_hold`` (times ``probe_backoff`` per failure in
  a row, up to ``ceiling_hold_max``; 1 by default: on ``dev`` a longer wait did
  not pay); the next probes step at most halfway to the rate that failed.

Rates are whole Hz: subscribers at one rate tick in step and share one encoded
snapshot per tick (``server.room``), and each change costs a compact subscriber a
key snapshot. Off by default: a subscriber that asks a number gets that number,
as before. :class:`AutoRates` is the glue the relay runs after each room tick;
``/metrics`` shows the chosen rates (``posecast_auto_rate_hz``).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Generic, Protocol, TypeVar

from posecast.protocol import Join, RateNotice
from posecast.server.histogram import bucket, histogram_lines
from posecast.server.link import Downlink
from posecast.server.view_rates import ViewState

if TYPE_CHECKING:
    from posecast.server.config import ServerConfig

__all__ = [
    "RATE_BUCKETS",
    "AutoRates",
    "Egress",
    "LinkRate",
    "RateHistogram",
    "adapter",
    "attach",
    "granted",
]

#: Upper bounds (Hz) of the chosen-rate histogram's buckets (``RateHistogram``).
RATE_BUCKETS = (5.0, 7.5, 10.0, 12.5, 15.0, 20.0, 25.0, 30.0, 45.0, 60.0)


@dataclass(frozen=True, slots=True)
class Egress:
    """One subscriber's egress counters (cumulative, except ``backlog``)."""

    #: Member ticks that came due with something to send (offered or skipped).
    ticks: int
    #: Of those, the snapshots that did not go (see the module docstring).
    skips: int
    #: Bytes that left the relay towards it.
    drained: int
    #: Bytes waiting in its socket's write buffer now.
    backlog: int = 0


@dataclass
class LinkRate:
    """One subscriber's rate controller (see the module docstring); time is passed in."""

    lo: float
    hi: float
    #: The rate it starts at (None: ``hi``, then down fast if the link is narrower).
    start: float | None = None
    window: float = 0.5
    headroom: float = 0.95
    down_factor: float = 0.85
    backlog_frames: float = 4.0
    up_after: float = 1.0
    up_every: float = 0.5
    up_step: float = 0.25
    ceiling_hold: float = 10.0
    #: A lone skip (none in the ``isolated_s`` before it, no probe on trial, no
    #: backlog) marks the rate as the link's edge: the rate stays, no step up.
    isolated_s: float = 3.0
    #: Each probe that fails in a row multiplies the hold before the next by this,
    #: up to ``ceiling_hold_max``.
    probe_backoff: float = 1.0
    ceiling_hold_max: float = 40.0
    rate: float = field(init=False)
    #: The rate that last failed and when (inf: none known).
    ceiling: float = field(init=False, default=math.inf)
    ceiling_at: float = field(init=False, default=-math.inf)
    #: Bytes per delivered snapshot (EMA; None: none delivered yet).
    frame_bytes: float | None = field(init=False, default=None)
    changes: int = field(init=False, default=0)
    congestions: int = field(init=False, default=0)
    #: Decision windows closed so far (each one an observation of ``posecast_auto_rate_hz``).
    windows: int = field(init=False, default=0)
    _last: tuple[float, Egress] | None = field(init=False, default=None)
    _changed_at: float = field(init=False, default=-math.inf)
    _down_at: float = field(init=False, default=-math.inf)
    #: The rate before the last step up (None: the last change was no step up).
    _probe: float | None = field(init=False, default=None)
    #: How long the ceiling holds now (``ceiling_hold``, longer after failed probes).
    _hold: float = field(init=False, default=0.0)
    #: No step up before this time (after a failed probe).
    _blocked_until: float = field(init=False, default=-math.inf)
    #: The last rate a probe failed at (kept after its ceiling expired: the next
    #: probes step towards it by halves).
    _failed_probe: float = field(init=False, default=math.inf)
    _skip_at: float = field(init=False, default=-math.inf)
    #: Lone skips seen (the rate stayed).
    edges: int = field(init=False, default=0)

    def __post_init__(self) -> None:
        if not 0 < self.lo <= self.hi:
            raise ValueError(f"LinkRate needs 0 < lo <= hi, got [{self.lo:g}, {self.hi:g}]")
        self.rate = self._whole(self.hi if self.start is None else self.start)
        self._hold = self.ceiling_hold

    def _whole(self, rate: float) -> float:
        """``rate`` in whole Hz, within [lo, hi] (lo and hi themselves are kept as given)."""
        return min(self.hi, max(self.lo, float(math.floor(rate + 1e-9))))

    def update(self, now: float, egress: Egress, relay_late: bool = False) -> float | None:
        """The new rate if it changes now (None: it stays); ``relay_late``: the relay
        itself runs late (its rooms grew past what it carries), a step down."""
        last = self._last
        if last is None or egress.ticks < last[1].ticks:  # first call, or counters reset
            self._last = (now, egress)
            return None
        t0, e0 = last
        dt = now - t0
        if dt < self.window:
            return None
        self._last = (now, egress)
        self.windows += 1
        ticks, skips = egress.ticks - e0.ticks, egress.skips - e0.skips
        drained = max(0, egress.drained - e0.drained)
        delivered = ticks - skips
        if delivered > 0 and drained > 0:
            sample = drained / delivered
            old = self.frame_bytes
            self.frame_bytes = sample if old is None else 0.7 * old + 0.3 * sample
        size = self.frame_bytes
        backlogged = size is not None and egress.backlog > self.backlog_frames * size
        if skips > 0 or backlogged or relay_late:
            if now - self._down_at < 2.0 * self.window:
                return None  # what queued before the last step down is still draining
            lone = skips == 1 and not backlogged and now - self._skip_at >= self.isolated_s
            lone = lone and not relay_late
            if lone and not self._on_trial(now):
                self._edge(now)
                return None
            return self._down(now, drained / dt)
        return self._up(now)

    def _on_trial(self, now: float) -> bool:
        """Whether the last change was a step up made within ``2 up_every``."""
        return self._probe is not None and now - self._changed_at <= 2.0 * self.up_every

    def _edge(self, now: float) -> None:
        """A lone skip: the link carries about this rate. Stay, and hold the next
        rate up as the ceiling (a step up would fail)."""
        self.edges += 1
        self._skip_at = now
        self.ceiling, self.ceiling_at = min(self.ceiling, self.rate + 1.0), now

    def _down(self, now: float, drain: float) -> float | None:
        self.congestions += 1
        failed = self.rate
        self.ceiling, self.ceiling_at = failed, now
        self._down_at = now
        if self._on_trial(now):
            # A step up failed at once: back to the rate that was fine before it, and
            # wait longer each time before the next try.
            assert self._probe is not None
            self._failed_probe = failed
            self._hold = min(self.ceiling_hold_max, self._hold * self.probe_backoff)
            self._blocked_until = now + self._hold
            return self._set(now, self._probe)
        # The link changed under a rate that held: probes as usual after the recovery.
        self._hold, self._blocked_until = self.ceiling_hold, -math.inf
        # What the drain carried (the link's measure), at least 1 Hz down; without
        # a measure yet, down by ``down_factor``.
        target = failed * self.down_factor
        if self.frame_bytes:
            target = min(failed - 1.0, self.headroom * drain / self.frame_bytes)
        return self._set(now, self._whole(target))

    def _up(self, now: float) -> float | None:
        if now - self.ceiling_at < self.up_after or now - self._changed_at < self.up_every:
            return None
        if self.rate >= self.hi or now < self._blocked_until:
            return None
        if self._probe is not None:  # the last step up held: probes may come sooner
            self._hold = self.ceiling_hold
        if now - self.ceiling_at >= self._hold:
            self.ceiling = math.inf  # an old limit: the link may have widened
        step = max(1.0, math.floor(self.rate * self.up_step))
        if self.rate < self._failed_probe < math.inf:  # halfway to where a probe failed
            step = min(step, max(1.0, math.floor((self._failed_probe - self.rate) / 2)))
        else:
            self._failed_probe = math.inf
        target = self._whole(self.rate + step)
        if target >= self.ceiling:
            target = self._whole(self.ceiling - 1.0)
        if target <= self.rate:
            return None
        was = self.rate
        self._set(now, target)
        self._probe = was
        return target

    def _set(self, now: float, rate: float) -> float | None:
        self._probe = None
        if rate == self.rate:
            return None
        self.rate, self._changed_at = rate, now
        self.changes += 1
        return rate


@dataclass
class RateHistogram:
    """The rates auto-rate subscribers were served at: one observation per subscriber
    per decision window (so the distribution is over subscriber time), per bucket of
    ``RATE_BUCKETS`` then +Inf (not cumulative), their sum (Hz), and rate changes."""

    counts: list[int] = field(default_factory=lambda: [0] * (len(RATE_BUCKETS) + 1))
    total: float = 0.0
    changes: int = 0
    #: Of the changes, the steps down made because the relay itself ran late.
    relay_late: int = 0

    def observe(self, rate: float) -> None:
        self.counts[bucket(rate, RATE_BUCKETS)] += 1
        self.total += rate

    def metric_lines(self, members: int) -> list[str]:
        """Prometheus text: the histogram, the changes counter, the members gauge."""
        lines = histogram_lines(
            "posecast_auto_rate_hz",
            "Snapshot rate the relay chose for each auto-rate subscriber"
            ' (join rate "auto"), observed once per subscriber per 0.5 s decision window.',
            RATE_BUCKETS,
            self.counts,
            self.total,
        )
        lines += [
            "# HELP posecast_auto_rate_changes_total Rate changes the relay told auto-rate "
            "subscribers (rate messages).",
            "# TYPE posecast_auto_rate_changes_total counter",
            f"posecast_auto_rate_changes_total {self.changes}",
            "# HELP posecast_auto_rate_relay_late_total Rates the relay lowered because its "
            "own ticks ran late (its rooms grew past what it carries), not for the link.",
            "# TYPE posecast_auto_rate_relay_late_total counter",
            f"posecast_auto_rate_relay_late_total {self.relay_late}",
            "# HELP posecast_auto_rate_members Members whose rate the relay chooses now.",
            "# TYPE posecast_auto_rate_members gauge",
            f"posecast_auto_rate_members {members}",
        ]
        return lines


def granted(max_rate: float, join: Join) -> float:
    """The rate a join is granted at first: its own, or an auto rate's start (its
    ``max_rate``, else the server's ``max_rate``: it comes down fast if need be)."""
    if not join.auto_rate:
        return float(join.rate)
    return join.max_rate if join.max_rate is not None else max_rate


class RatedOutbox(Protocol):
    """What the rate rules read of a connection's outbox (``server.member.Outbox``)."""

    @property
    def snapshots_offered(self) -> int: ...
    @property
    def skips(self) -> int: ...
    @property
    def buffered(self) -> int: ...


class RatedPeer(Protocol):
    """What the rate rules use of a connection (``server.peer.Peer``): its counters,
    and its emulated downlink, which :func:`attach` sets."""

    downlink: Downlink | None

    @property
    def user(self) -> int | None: ...
    @property
    def outbox(self) -> RatedOutbox: ...
    @property
    def bytes_out(self) -> int: ...


class RatedMember(Protocol):
    """What the rate rules use of a room's member (``server.member.Member``)."""

    rate: float
    asked_rate: float
    link_rate: LinkRate | None
    view: ViewState | None

    @property
    def user(self) -> int: ...
    @property
    def parked(self) -> bool: ...
    @property
    def compact(self) -> bool: ...
    @property
    def congestion_skips(self) -> int: ...


class RatedRoom(Protocol):
    """What :class:`AutoRates` uses of a room (``server.room.Room``)."""

    @property
    def members(self) -> Mapping[int, RatedMember]: ...
    def set_rate(self, user: int, rate: float, now: float) -> None: ...


def attach(config: ServerConfig, peer: RatedPeer, member: RatedMember, join: Join) -> None:
    """Give a joining member its rate controls: the emulated link (``serve --link``),
    for ``rate="auto"`` a :class:`LinkRate` from the server's min to its ceiling, and
    for ``budget_deg`` its per-peer schedule (``server.view_rates``)."""
    member.asked_rate = member.rate
    if config.link is not None:
        assert peer.user is not None
        peer.downlink = Downlink(
            config.link, peer.user, config.link_max_in_flight, in_order=member.compact
        )
    member.link_rate = (
        LinkRate(config.min_rate, member.rate, start=member.rate) if join.auto_rate else None
    )
    budget = join.budget_deg if config.view_rates else None
    member.view = ViewState(budget) if budget is not None else None


def egress(peer: RatedPeer, member: RatedMember) -> Egress:
    """``member``'s egress counters as its connection ``peer`` has them."""
    outbox, downlink = peer.outbox, peer.downlink
    ticks = outbox.snapshots_offered + member.congestion_skips
    skips = outbox.skips + member.congestion_skips
    if downlink is not None:  # the emulated link is the bottleneck: what passed its cap
        link = downlink.link
        return Egress(ticks, skips + link.cap_skips, link.bytes)
    backlog = outbox.buffered
    return Egress(ticks, skips, peer.bytes_out - backlog, backlog)


P = TypeVar("P", bound=RatedPeer)


class Pressure(Protocol):
    """Whether the relay runs late for its members' work (``server.capacity.Capacity``)."""

    def overloaded(self, now: float) -> bool: ...


class RelayView(Protocol[P]):
    """What :class:`AutoRates` needs of the relay core (``server.core.RelayCore``)."""

    @property
    def capacity(self) -> Pressure: ...

    def connected(self, user: int) -> P | None: ...

    def send(self, peer: P, message: RateNotice) -> None: ...


class AutoRates(Generic[P]):
    """What the relay runs after each room's tick (``server.rooms.RoomTable.adapt``):
    each auto-rate member's controller decides, from its link and from whether the
    relay itself runs late; a new rate moves the member (the caller schedules the
    room after) and is told to the client. Keeps the rates' histogram for ``/metrics``."""

    def __init__(self, core: RelayView[P]) -> None:
        self.core = core
        self.histogram = RateHistogram()

    def __call__(self, room: RatedRoom, now: float) -> None:
        core, hist = self.core, self.histogram
        late: bool | None = None  # (asked once a tick, and only of a room with auto rates)
        for member in room.members.values():
            ctl = member.link_rate
            if ctl is None or member.parked:
                continue
            peer = core.connected(member.user)
            if peer is None:
                continue
            if late is None:
                late = core.capacity.overloaded(now)
            windows, served = ctl.windows, ctl.rate
            rate = ctl.update(now, egress(peer, member), late)
            if ctl.windows != windows:
                hist.observe(served)
            if rate is not None and rate != member.rate:
                hist.changes += 1
                hist.relay_late += late and rate < served
                room.set_rate(member.user, rate, now)
                core.send(peer, RateNotice(rate=rate))

    def metric_lines(self, rooms: Iterable[RatedRoom]) -> list[str]:
        members = sum(m.link_rate is not None for r in rooms for m in r.members.values())
        return self.histogram.metric_lines(members)


def adapter(core: RelayView[P]) -> AutoRates[P]:
    """The :class:`AutoRates` of ``core``'s rooms."""
    return AutoRates(core)
