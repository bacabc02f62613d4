"""The receiver's timing, sans I/O: clock offset and adaptive playout delay.

Nothing here reads a clock: every method takes the time it needs.

- :class:`ClockEstimator`: NTP-style offset to the server clock from ping/pong
  samples, keeping the lowest round trip of a sliding window.
- :class:`PlayoutDelay`: delay D that starts at one interval plus the measured
  arrival jitter and follows the observed keyframe age (Mirror-style dynamic
  buffer: ``D = interval + p95(age)``), slewing smoothly, never jumping.
- :class:`RoomPlayoutDelay`: a :class:`PlayoutDelay` per remote user, the room's
  D from the users whose ages are not outliers (the majority's median plus a
  bound that follows the room's own jitter width, or the MAD of the medians); a
  late user is shown late alone, at its own D; with ``per_peer``, a user whose
  keyframes come every k snapshot intervals (the relay's view-aware rates) is
  shown k - 1 intervals later than the room's D.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

__all__ = ["ClockEstimator", "PlayoutDelay", "RoomPlayoutDelay"]


def _median(ranked: list[float]) -> float:
    """numpy's median of sorted values, the same bits (a mean of the middle two)."""
    n = len(ranked)
    mid = n // 2
    return ranked[mid] if n % 2 else (ranked[mid - 1] + ranked[mid]) / 2.0


def _percentile(ranked: list[float], q: float) -> float:
    """numpy's default (linear) percentile of sorted values, the same bits: numpy's
    call costs tens of microseconds, this is done per user at every classification."""
    n = len(ranked)
    pos = (n - 1) * (q / 100.0)
    lo = math.floor(pos)
    hi = min(lo + 1, n - 1)
    t = pos - lo
    a, b = ranked[lo], ranked[hi]
    return b - (b - a) * (1.0 - t) if t >= 0.5 else a + (b - a) * t


@dataclass
class ClockEstimator:
    """Server-minus-client clock offset from the lowest-RTT recent ping sample."""

    window: int = 16
    _samples: deque[tuple[float, float]] = field(default_factory=deque)

    def add(self, offset: float, rtt: float) -> None:
        self._samples.append((rtt, offset))
        while len(self._samples) > self.window:
            self._samples.popleft()

    @property
    def ready(self) -> bool:
        return bool(self._samples)

    @property
    def offset(self) -> float:
        return min(self._samples)[1] if self._samples else 0.0

    @property
    def rtt(self) -> float:
        return min(self._samples)[0] if self._samples else float("nan")


@dataclass
class PlayoutDelay:
    """Adaptive playout delay D (seconds) from the ages of arriving keyframes."""

    interval: float
    #: Share of keyframe ages the delay covers.
    percentile: float = 95.0
    #: Time constant of the slew towards the target (s).
    tau: float = 1.0
    window: int = 256
    margin: float = 0.002
    value: float = field(init=False)
    _ages: deque[float] = field(init=False)
    _last: float | None = None

    def __post_init__(self) -> None:
        self.value = self.interval + self.margin
        self._ages = deque(maxlen=self.window)

    def observe(self, age: float) -> None:
        """One keyframe's age on arrival (arrival minus capture, server clock)."""
        self._ages.append(age)

    @property
    def target(self) -> float:
        if not self._ages:
            return self.interval + self.margin
        return self.interval + float(np.percentile(self._ages, self.percentile)) + self.margin

    def update(self, now: float, target: float | None = None) -> float:
        """Slew towards its target (or ``target``); the first one sets D directly."""
        given = target is not None
        target = self.target if target is None else target
        if self._last is None:
            if self._ages or given:
                self.value = target
                self._last = now
            return self.value
        dt = max(0.0, now - self._last)
        self._last = now
        self.value += (target - self.value) * min(1.0, dt / self.tau)
        return self.value


@dataclass
class RoomPlayoutDelay:
    """Playout delay per remote user: one late user cannot raise D for the others.

    Ages (arrival minus capture, server clock) are kept per user (its streams share
    its clock and path), each in a :class:`PlayoutDelay`. The late bound follows the
    room's own spread of ages::

        ref   = lower median of the users' median ages (the majority's)
        width = lower median of the users' (percentile age - median age)
        phase = one snapshot interval (``phase``)
        bound = max(tolerance, jitter * width) + phase
                + spread * 1.4826 * max(0, MAD(medians) - phase / 2)

    A user is *late* when its median age exceeds ``ref + bound + 3 * width / sqrt(n)``
    (``n`` its ages, at least ``settle``: the median of few ages is uncertain, and
    a user with fewer is late only beyond ``early``, 100 ms). Honest medians differ
    by up to one snapshot interval from the phase of each publisher against the
    relay's ticks (measured on loopback: 4 and 32 ms at 15 Hz), so ``phase`` is
    always allowed, and the MAD of the medians counts only beyond it: a room whose
    paths differ widely keeps one D (the MAD term). A lag under about one interval
    cannot be told from a later phase and is not judged late: it raises D by up to
    the lag plus the phase gap, about one interval. A late user stays late until
    its median is back under that bound and its ``percentile`` age under the room's
    plus ``bound`` (its late ages have left its window). The room's D covers the
    ``percentile`` of the pooled ages of users not late; it is set, not slewed,
    when none of the users it shows was shown with it before. A late user is shown
    late alone at its own D (``own``), slewing from where it was shown to
    ``max(room's target, its own)``; no longer late, it slews back and rejoins the
    room's D within 1 ms. Users with under ``min_samples`` ages are not judged.

    Per peer (``per_peer``, for a client that joined with ``budget_deg``: the relay
    then sends each peer every ``k`` snapshot intervals, its own ``k``, section 5.6
    of the protocol): the send times of the snapshots that carry a user's new
    keyframes say its keyframe interval in snapshot intervals (``round(gap *
    rate)`` half up, at least 1; the last ``gap_window`` of them). Its divisor ``k`` is their
    ``percentile`` (nearest rank), and its D is the one above plus ``(k - 1) *
    interval`` (the bracket it must bridge is k times longer; ``interval`` holds a
    window method's look-ahead too), that extra slewing like any D (set at once for
    a user's first gap). A user whose keyframes come at the snapshot rate has k = 1
    and exactly the D it had without ``per_peer``. Ages stay as they are: they
    measure the path, not the interval.
    """

    interval: float
    percentile: float = 95.0
    tau: float = 1.0
    window: int = 256
    margin: float = 0.002
    #: Floor of the late bound (s), for rooms with almost no jitter.
    tolerance: float = 0.005
    #: Share of the room's jitter width (percentile minus median age) a lag may reach.
    jitter: float = 0.3
    spread: float = 3.0
    min_samples: int = 3
    #: Honest spread of median ages from the publishers' phases against the relay's
    #: ticks (s); None: one snapshot interval (1 / ``rate``, else ``interval``).
    phase: float | None = None
    #: Ages a user needs to be judged by the room's spread; before, by ``early`` (s).
    settle: int = 20
    early: float = 0.1
    #: The snapshot rate ``interval`` is for (Hz; None: not given, :meth:`retime` does nothing).
    rate: float | None = None
    #: Size each user's D from its own keyframe interval too (see the class docstring).
    per_peer: bool = False
    #: Keyframe intervals (in snapshot intervals) a user's divisor is judged over.
    gap_window: int = 16
    room: PlayoutDelay = field(init=False)
    #: Users shown late alone (or slewing back to the room's D): their own D (s).
    own: dict[int, float] = field(default_factory=dict)
    late: set[int] = field(default_factory=set)
    _users: dict[int, PlayoutDelay] = field(default_factory=dict)
    _dirty: bool = False
    _target: float | None = None
    #: Late users' own targets; users shown at the room's D (now, and before).
    _own: dict[int, float] = field(default_factory=dict)
    _seated: set[int] = field(default_factory=set)
    _was: set[int] = field(default_factory=set)
    #: Per peer: each user's last send time carrying its keyframes, its gaps (in
    #: snapshot intervals), its extra D (s) and when the extras last slewed.
    _sent: dict[int, float] = field(default_factory=dict)
    _gaps: dict[int, deque[int]] = field(default_factory=dict)
    _extra: dict[int, float] = field(default_factory=dict)
    _extra_at: float | None = None

    def __post_init__(self) -> None:
        self.room = self._new()

    def _new(self) -> PlayoutDelay:
        return PlayoutDelay(self.interval, self.percentile, self.tau, self.window, self.margin)

    def retime(self, rate: float) -> None:
        """The snapshots now come at ``rate`` (Hz): every interval D covers scales with it."""
        if self.rate is None or rate <= 0:
            return
        scale, self.rate = self.rate / rate, rate
        self.interval *= scale
        for d in (self.room, *self._users.values()):
            d.interval *= scale
        self._gaps.clear()  # counted in the old intervals; the extras slew from where they are
        self._dirty = True

    def observe(self, user: int, age: float, sent: float | None = None) -> None:
        """One keyframe of ``user``'s, its age on arrival (server clock); ``sent``: the
        send time of the snapshot that carried it (server clock; used ``per_peer``)."""
        (self._users.get(user) or self._users.setdefault(user, self._new())).observe(age)
        self._dirty = True
        if self.per_peer and sent is not None:
            last = self._sent.get(user)
            if last is None or sent > last:
                self._sent[user] = sent
            if last is not None and sent > last:
                gaps = self._gaps.get(user) or self._gaps.setdefault(
                    user, deque(maxlen=self.gap_window)
                )
                gaps.append(max(1, math.floor((sent - last) / self._interval() + 0.5)))

    def divisor(self, user: int) -> int:
        """``user``'s keyframe interval in snapshot intervals (1 without ``per_peer``)."""
        gaps = self._gaps.get(user)
        if not gaps:
            return 1
        ranked = sorted(gaps)  # nearest rank: the ceil(n p / 100)-th smallest
        return ranked[max(0, math.ceil(len(ranked) * self.percentile / 100) - 1)]

    def own_delays(self) -> dict[int, float]:
        """Every user shown at another D than the room's: late ones, slower peers."""
        out = dict(self.own)
        for u, e in self._extra.items():
            if e > 1e-9:
                out[u] = self.own.get(u, self.room.value) + e
        return out

    def forget(self, user: int) -> None:
        """A user left: its ages no longer count."""
        self._users.pop(user, None)
        self.own.pop(user, None)
        self.late.discard(user)
        self._sent.pop(user, None)
        self._gaps.pop(user, None)
        self._extra.pop(user, None)
        self._dirty = True

    def delay(self, user: int) -> float:
        """The D ``user``'s streams are rendered with."""
        return self.own.get(user, self.room.value) + self._extra.get(user, 0.0)

    def _interval(self) -> float:
        return 1.0 / self.rate if self.rate else self.interval

    def _classify(self) -> float | None:
        """Judge every user with enough ages; the room's target (None: no ages)."""
        judged = {u: d for u, d in self._users.items() if len(d._ages) >= self.min_samples}
        if judged:
            ages = {u: sorted(d._ages) for u, d in judged.items()}
            med = {u: _median(a) for u, a in ages.items()}
            top = {u: _percentile(a, self.percentile) for u, a in ages.items()}
            ranked = sorted(med.values())
            ref = ranked[(len(ranked) - 1) // 2]
            widths = sorted(top[u] - med[u] for u, a in ages.items() if len(a) >= self.settle)
            width = widths[(len(widths) - 1) // 2] if widths else 0.0
            mad = float(np.median(np.abs(np.array(ranked) - ref))) if len(ranked) > 2 else 0.0
            phase = self.phase if self.phase is not None else self._interval()
            paths = self.spread * 1.4826 * max(0.0, mad - phase / 2)
            bound = max(self.tolerance, self.jitter * width) + phase + paths
            over = {
                u: med[u] - ref
                > (bound + 3.0 * width / len(a) ** 0.5 if len(a) >= self.settle else self.early)
                for u, a in ages.items()
            }
            self.late |= {u for u, o in over.items() if o}
            seated = [ages[u] for u in judged if u not in self.late]
            room = float(np.percentile(np.concatenate(seated), self.percentile)) if seated else ref
            for u in self.late & judged.keys():
                if not over[u] and top[u] < room + bound:
                    self.late.discard(u)  # the late ages have left its window
        self._own = {u: self._users[u].target for u in self.late}
        seated_users = {u for u in judged if u not in self.late}
        if seated_users and not seated_users & self._seated:
            self.room._last = None  # nobody shown at the room's D stays: set it
        self._was, self._seated = self._seated, seated_users
        pool = [d._ages for u, d in judged.items() if u in seated_users] or [
            d._ages for d in self._users.values() if d._ages
        ]
        if not pool:
            return None
        pooled = np.concatenate([np.fromiter(a, float, len(a)) for a in pool])
        return self.interval + float(np.percentile(pooled, self.percentile)) + self.margin

    def update(self, now: float) -> float:
        """Slew the room's D and every late user's own D; returns the room's."""
        before = self.room.value
        if self._dirty:
            self._target, self._dirty = self._classify(), False
        target = self._target
        room = self.room.update(now, target)
        for u in self.late - self.own.keys():  # newly late: from where it was shown
            d = self._users[u]
            d.value, d._last = before, (now if u in self._was else None)
        for u in list(self.own.keys() | self.late):
            d = self._users[u]
            if u in self.late:
                self.own[u] = d.update(now, max(self._own[u], target or room))
            elif abs(d.update(now, room) - room) < 1e-3:
                del self.own[u]  # back in step with the room
            else:
                self.own[u] = d.value
        if self._gaps:
            self._slew_extras(now)
        return room

    def _slew_extras(self, now: float) -> None:
        """Each slower peer's extra D towards ``(k - 1) * interval``."""
        dt = 0.0 if self._extra_at is None else max(0.0, now - self._extra_at)
        step = 1.0 if self._extra_at is None else min(1.0, dt / self.tau)
        self._extra_at = now
        for u in self._gaps:
            goal = (self.divisor(u) - 1) * self.interval
            e = self._extra.get(u)
            self._extra[u] = goal if e is None else e + (goal - e) * step
