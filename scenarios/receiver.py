"""The receiver model: clock offset, jitter buffers, adaptive playout delay.

Shared by the live bots and the offline simulator; nothing here reads a clock
(every method takes the time it needs).

- :class:`ClockEstimator`: NTP-style offset to the server clock from ping/pong
  samples, keeping the lowest round trip of a sliding window.
- :class:`RoomBuffers`: every remote stream's keyframes in one preallocated
  array per room (a row per stream), validated once on arrival.
- :class:`StreamBuffer`: one remote stream's keyframes ordered by capture time
  (a row of a room), each with the velocity it came with (zeros without one);
  duplicates and stale frames dropped; bounded (oldest evicted).
- :class:`PlayoutDelay`: delay D that starts at one interval plus the measured
  arrival jitter and follows the observed keyframe age (Mirror-style dynamic
  buffer: ``D = interval + p95(age)``), slewing smoothly, never jumping.
- :class:`RoomPlayoutDelay`: a :class:`PlayoutDelay` per remote user, the room's
  D from the users whose ages are not outliers (median + MAD); a late user is
  shown late alone, at its own D.
- :func:`render_buffers`: every buffer at its playout time: one vectorised
  bracket of all streams, one gather, one batched interpolator call per
  method (a pair method's allocation-free row kernel), window and velocity
  methods alike.
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from functools import partial
from typing import NamedTuple, cast

import numpy as np
from numpy.typing import NDArray

from interp import InterpolatorInfo, interpolate_brackets
from interp import info as interp_info
from interp.kernels import SHARES_PRODUCTS, share_rows
from interp.pose import UNIT_TOLERANCE
from scenarios.motion import MotionSpec
from scenarios.qoe import ErrorSamples, KeyframeLog, evaluate_group, window_depth
from scenarios.traces import Trace, TraceError

__all__ = [
    "DEFAULT_BUFFER_CAPACITY",
    "VELOCITY_FALLBACK",
    "ClockEstimator",
    "PlayoutDelay",
    "ReceivedStream",
    "RenderFrame",
    "RoomBuffers",
    "RoomPlayoutDelay",
    "StreamBuffer",
    "render_buffers",
    "rendered_method",
    "score_received",
]

F64 = NDArray[np.float64]

DEFAULT_BUFFER_CAPACITY = 64

#: The velocity of a keyframe that came without one (shared, read-only).
_NO_VELOCITY = np.zeros(6)
_NO_VELOCITY.setflags(write=False)


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


class RoomBuffers:
    """The keyframes of every remote stream of a room, in preallocated arrays.

    One row per stream (:meth:`stream` adds one and returns its
    :class:`StreamBuffer`), ``capacity + 1`` slots per row, in capture-time order
    and padded with ``+inf`` times: ``times (R, W)``, ``poses (7, R, W)``
    (component major, float64, validated on arrival: finite, unit quaternions),
    ``velocities (R, W, 6)``, ``counts (R,)`` and ``has_velocities (R,)``. The
    arrays grow (doubling the rows) when streams are added; a render frame
    (:func:`render_buffers`) brackets every row with one vectorised comparison
    and gathers the bracketing keyframes with one ``take`` per side.
    """

    def __init__(self, capacity: int = DEFAULT_BUFFER_CAPACITY, streams: int = 16) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be at least 1, got {capacity}")
        self.capacity = capacity
        self.width = capacity + 1  # a spare slot: insert first, then evict
        self.n = 0  # rows in use
        self.times: F64
        self.poses: F64
        self.velocities: F64
        self.counts: NDArray[np.intp]
        self.has_velocities: NDArray[np.bool_]
        #: Per row: its index, the flat index of its slot 0 and of its newest keyframe.
        self.row_index: NDArray[np.intp]
        self.base: NDArray[np.intp]
        self.newest: NDArray[np.intp]
        self._allocate(max(1, streams))

    def _allocate(self, rows: int) -> None:
        w, n = self.width, self.n
        times = np.full((rows, w), np.inf)
        poses = np.zeros((7, rows, w))
        vels = np.zeros((rows, w, 6))
        counts = np.zeros(rows, dtype=np.intp)
        has_v = np.ones(rows, dtype=bool)
        if n:
            times[:n] = self.times[:n]
            poses[:, :n] = self.poses[:, :n]
            vels[:n] = self.velocities[:n]
            counts[:n] = self.counts[:n]
            has_v[:n] = self.has_velocities[:n]
        self.times, self.poses, self.velocities = times, poses, vels
        self.counts, self.has_velocities = counts, has_v
        self.row_index = np.arange(rows, dtype=np.intp)
        self.base = self.row_index * w
        self.newest = self.base + counts - 1

    def stream(self, capacity: int | None = None, *, has_velocities: bool = True) -> StreamBuffer:
        """A new stream's buffer, backed by the next row."""
        return StreamBuffer(capacity, has_velocities=has_velocities, room=self)

    def _add_row(self, has_velocities: bool) -> int:
        if self.n == self.counts.shape[0]:
            self._allocate(2 * self.n)
        row = self.n
        self.n += 1
        self.has_velocities[row] = has_velocities
        return row

    def __len__(self) -> int:
        """Streams (rows) in use, empty ones included."""
        return self.n

    def _insert(
        self, row: int, i: int, capture: float, pose: F64, velocity: NDArray[np.float64] | None
    ) -> None:
        """Put a keyframe at slot ``i`` of ``row``, shifting later ones right."""
        c = int(self.counts[row])
        times, poses, vels = self.times, self.poses, self.velocities
        if i < c:
            times[row, i + 1 : c + 1] = times[row, i:c]
            poses[:, row, i + 1 : c + 1] = poses[:, row, i:c]
            vels[row, i + 1 : c + 1] = vels[row, i:c]
        times[row, i] = capture
        poses[:, row, i] = pose
        vels[row, i] = 0.0 if velocity is None else velocity
        self.counts[row] = c + 1
        self.newest[row] += 1

    def _evict_oldest(self, row: int) -> None:
        c = int(self.counts[row])
        times, poses, vels = self.times, self.poses, self.velocities
        times[row, : c - 1] = times[row, 1:c]
        poses[:, row, : c - 1] = poses[:, row, 1:c]
        vels[row, : c - 1] = vels[row, 1:c]
        times[row, c - 1] = np.inf
        self.counts[row] = c - 1
        self.newest[row] -= 1


def _checked_pose(pose: NDArray[np.float32]) -> F64 | None:
    """A keyframe pose as float64, its quaternion renormalised when it is off unit
    length by more than ``interp``'s tolerance; None when it is not finite or the
    quaternion is zero (such a keyframe could only break every render)."""
    p = np.asarray(pose, dtype=np.float64).reshape(7)
    x = p.tolist()
    n2 = x[3] * x[3] + x[4] * x[4] + x[5] * x[5] + x[6] * x[6]
    if not (math.isfinite(sum(x)) and all(map(math.isfinite, x))) or not n2 > 1e-24:
        return None
    if abs(n2 - 1.0) > 2.0 * UNIT_TOLERANCE:
        p = p.copy()
        p[3:] /= math.sqrt(n2)
    return p


class StreamBuffer:
    """Keyframes of one remote stream, by capture time, for rendering.

    ``push`` refuses duplicates (same capture time) and stale keyframes: ones
    that can never be a bracket again because a newer keyframe already sits at
    or before ``floor`` (the playout time already passed), or that are older than
    everything kept in a full buffer. A late keyframe just before the playout
    time is kept: it is the lower bracket. Beyond ``capacity`` the oldest is
    evicted. A pose that is not finite or has a zero quaternion is refused
    (``invalid``).

    ``velocities[i]`` is the velocity ``(6,)`` (linear m/s, angular rad/s, world
    frame) that came with ``times[i]``/``poses[i]``, for velocity interpolators;
    a keyframe pushed without one gets zeros. ``has_velocities`` says whether the
    sender reports velocities at all: if not, the zeros are fillers, not data,
    and velocity methods render the stream with :data:`VELOCITY_FALLBACK`.

    The keyframes live in one row of a :class:`RoomBuffers` (``room``; a buffer
    made on its own gets a room of its own); the lists here mirror that row.
    """

    def __init__(
        self,
        capacity: int | None = DEFAULT_BUFFER_CAPACITY,
        *,
        has_velocities: bool = True,
        room: RoomBuffers | None = None,
    ) -> None:
        if room is None:
            room = RoomBuffers(DEFAULT_BUFFER_CAPACITY if capacity is None else capacity, 1)
        capacity = room.capacity if capacity is None else capacity
        if not 1 <= capacity <= room.capacity:
            raise ValueError(f"capacity must be in 1..{room.capacity}, got {capacity}")
        self.capacity = capacity
        self.room = room
        self.row = room._add_row(has_velocities)
        self.times: list[float] = []
        self.poses: list[NDArray[np.float32]] = []
        self.velocities: list[NDArray[np.float64]] = []
        self.duplicates = 0
        self.stale = 0
        self.evicted = 0
        self.invalid = 0

    @property
    def has_velocities(self) -> bool:
        return bool(self.room.has_velocities[self.row])

    @has_velocities.setter
    def has_velocities(self, value: bool) -> None:
        self.room.has_velocities[self.row] = value

    def push(
        self,
        capture: float,
        pose: NDArray[np.float32],
        floor: float = -np.inf,
        velocity: NDArray[np.float64] | None = None,
    ) -> bool:
        times = self.times
        i = bisect.bisect_left(times, capture)
        if i < len(times) and times[i] == capture:
            self.duplicates += 1
            return False
        superseded = capture < floor and i < len(times) and times[i] <= floor
        if superseded or (len(times) >= self.capacity and i == 0):
            self.stale += 1
            return False
        checked = _checked_pose(pose)
        if checked is None or not math.isfinite(capture):
            self.invalid += 1
            return False
        times.insert(i, capture)
        self.poses.insert(i, pose)
        self.velocities.insert(i, _NO_VELOCITY if velocity is None else velocity)
        self.room._insert(self.row, i, capture, checked, velocity)
        if len(times) > self.capacity:
            del times[0]
            del self.poses[0]
            del self.velocities[0]
            self.room._evict_oldest(self.row)
            self.evicted += 1
        return True

    def __len__(self) -> int:
        return len(self.times)

    def bracket(self, t: float) -> tuple[int, int, float, bool]:
        """``(lo, hi, s, stall)`` for playout time ``t`` (hold the newest on a stall).

        Before the first keyframe too: DESIGN.md's rule is "hold the newest".
        """
        times = self.times
        hi = bisect.bisect_right(times, t)
        if hi == 0:
            newest = len(times) - 1
            return newest, newest, 0.0, True
        lo = hi - 1
        if times[lo] == t:
            return lo, lo, 0.0, False
        if hi >= len(times):
            return lo, lo, 0.0, True
        return lo, hi, (t - times[lo]) / (times[hi] - times[lo]), False


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
    its clock and path), each in a :class:`PlayoutDelay`. A user is *late* when its
    median age exceeds the reference (the lower median of the users' medians) by
    over ``tolerance`` s, or ``spread`` robust deviations (1.4826 MAD) of the
    medians if larger, until its ``percentile`` age is back under that. The room's
    D covers the ``percentile`` of the pooled ages of users not late; it is set,
    not slewed, when none of the users it shows was shown with it before. A late
    user is shown late alone at its own D (``own``), slewing from where it was
    shown to ``max(room's target, its own)``; no longer late, it slews back and
    rejoins the room's D within 1 ms. Users with under ``min_samples`` ages are
    not judged.
    """

    interval: float
    percentile: float = 95.0
    tau: float = 1.0
    window: int = 256
    margin: float = 0.002
    tolerance: float = 0.1
    spread: float = 3.0
    min_samples: int = 3
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

    def __post_init__(self) -> None:
        self.room = self._new()

    def _new(self) -> PlayoutDelay:
        return PlayoutDelay(self.interval, self.percentile, self.tau, self.window, self.margin)

    def observe(self, user: int, age: float) -> None:
        """One keyframe of ``user``'s, its age on arrival (server clock)."""
        (self._users.get(user) or self._users.setdefault(user, self._new())).observe(age)
        self._dirty = True

    def forget(self, user: int) -> None:
        """A user left: its ages no longer count."""
        self._users.pop(user, None)
        self.own.pop(user, None)
        self.late.discard(user)
        self._dirty = True

    def delay(self, user: int) -> float:
        """The D ``user``'s streams are rendered with."""
        return self.own.get(user, self.room.value)

    def _classify(self) -> float | None:
        """Judge every user with enough ages; the room's target (None: no ages)."""
        judged = {u: d for u, d in self._users.items() if len(d._ages) >= self.min_samples}
        if judged:
            med = {u: float(np.median(d._ages)) for u, d in judged.items()}
            ranked = sorted(med.values())
            ref = ranked[(len(ranked) - 1) // 2]
            mad = float(np.median(np.abs(np.array(ranked) - ref))) if len(ranked) > 2 else 0.0
            bound = max(self.tolerance, self.spread * 1.4826 * mad)
            for u, m in med.items():
                if m > ref + bound:
                    self.late.add(u)
                elif u in self.late and judged[u].target < self.interval + ref + bound:
                    self.late.discard(u)  # the late ages have left its window
        self._own = {u: self._users[u].target for u in self.late}
        seated = {u for u in judged if u not in self.late}
        if seated and not seated & self._seated:
            self.room._last = None  # nobody shown at the room's D stays: set it
        self._was, self._seated = self._seated, seated
        pool = [d._ages for u, d in judged.items() if u in seated] or [
            d._ages for d in self._users.values() if d._ages
        ]
        if not pool:
            return None
        ages = np.concatenate([np.fromiter(a, float, len(a)) for a in pool])
        return self.interval + float(np.percentile(ages, self.percentile)) + self.margin

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
        return room


#: What a velocity method renders a stream with when its sender reports no
#: velocities (zero velocities would make a Hermite curve stop at every keyframe).
VELOCITY_FALLBACK = "motor-lerp"


def rendered_method(method: str, has_velocities: bool) -> str:
    """The method that actually renders a stream: ``method``, or the fallback for a
    velocity method on a stream without velocities."""
    if not has_velocities and interp_info(method).needs_velocity:
        return VELOCITY_FALLBACK
    return method


@dataclass(frozen=True)
class RenderFrame:
    """Rendered poses ``(S, 7)`` per method, and which streams stalled."""

    poses: dict[str, NDArray[np.float64]]
    stalled: NDArray[np.bool_]


class _Brackets(NamedTuple):
    """Every live row's bracket at one playout time, as flat slot indices."""

    lo: NDArray[np.intp]
    hi: NDArray[np.intp]
    #: Flat index of each row's slot 0, and its newest keyframe's.
    base: NDArray[np.intp]
    newest: NDArray[np.intp]
    s: F64
    stalled: NDArray[np.bool_]
    #: Whether any ``s`` is exactly 0 or 1 (held brackets are ``s == 0``).
    ends: bool


def _bracket_rows(
    room: RoomBuffers, rows: NDArray[np.intp], t: float | F64, whole: bool = False
) -> _Brackets:
    """Bracket ``rows`` (all non-empty) at ``t`` at once, as :meth:`StreamBuffer.bracket`.

    A row's times are sorted and padded with ``+inf`` (its last slot is always
    free), so its first time after ``t`` is the first ``False`` of ``times <= t``:
    ``bisect_right`` for every row from one comparison and one ``argmin``.
    ``t``: one playout time for every row, or one per row of ``rows`` ``(n,)``.
    ``whole``: ``rows`` is every row of the room, in order (views instead of copies).
    """
    n = rows.shape[0]
    if whole:
        times, base, newest = room.times[:n], room.base[:n], room.newest[:n]
    else:
        times, base, newest = room.times[rows], room.base[rows], room.newest[rows]
    tt: F64 | np.float64
    if isinstance(t, np.ndarray):
        tt, due = t, times <= t[:, None]
    else:
        tt = np.float64(t)
        due = times <= tt
    after = due.argmin(axis=1)  # slot of the first keyframe after t
    lo = base + after
    lo -= 1
    if np.count_nonzero(after) < n:  # nothing at or before t: hold the newest
        np.copyto(lo, newest, where=after == 0)
    flat = room.times.reshape(-1)
    t_lo = flat.take(lo)
    on = t_lo == tt  # exactly on a keyframe: show it, not a stall
    # Past the newest and not on it is a stall (before the first too: lo is the newest).
    at_end = lo == newest
    held = at_end | on
    stalled = np.greater(at_end, on)
    hi = lo + 1
    any_held = np.count_nonzero(held)
    if any_held:
        np.copyto(hi, lo, where=held)
    span = flat.take(hi)
    span -= t_lo
    if any_held:
        np.copyto(span, 1.0, where=held)
    s = tt - t_lo
    s /= span
    if any_held:
        np.copyto(s, 0.0, where=held)
    # Otherwise t_lo < t < t_hi, so 0 < s; s == 1 only by rounding (t a hair below t_hi).
    ends = bool(any_held) or bool(np.count_nonzero(s == 1.0))
    return _Brackets(lo, hi, base, newest, s, stalled, ends)


def _window(br: _Brackets, lb: int, la: int) -> NDArray[np.intp]:
    """Flat slots ``(lb + 2 + la, n)`` of each bracket's window (the rule of
    :mod:`interp.registry`: a missing neighbour, or any after a held bracket,
    repeats its inward neighbour)."""
    out = np.empty((lb + 2 + la, br.lo.shape[0]), dtype=np.intp)
    for j, i in enumerate(range(lb, 0, -1)):
        np.maximum(br.lo - i, br.base, out=out[j])
    out[lb], out[lb + 1] = br.lo, br.hi
    moving = br.hi > br.lo
    for i in range(1, la + 1):
        np.minimum(br.hi + i, br.newest, out=out[lb + 1 + i])
        np.copyto(out[lb + 1 + i], br.hi, where=~moving)
    return out


def _rows_of(
    buffers: Sequence[StreamBuffer] | RoomBuffers,
) -> tuple[RoomBuffers, NDArray[np.intp], bool]:
    """The room, the rows of the non-empty buffers in order, and whether they are
    all of the room's rows in order.

    Buffers of different rooms are copied into one temporary room first.
    """
    if isinstance(buffers, RoomBuffers):
        n = buffers.n
        counts = buffers.counts[:n]
        if np.count_nonzero(counts) == n:
            return buffers, buffers.row_index[:n], True
        return buffers, np.flatnonzero(counts), False
    live = [b for b in buffers if len(b)]
    if not live:
        return RoomBuffers(1, 1), np.zeros(0, dtype=np.intp), False
    room = live[0].room
    if all(b.room is room for b in live):
        rows = np.fromiter((b.row for b in live), dtype=np.intp, count=len(live))
        return room, rows, False
    n = len(live)
    joined = RoomBuffers(max(b.room.capacity for b in live), n)
    for j, b in enumerate(live):
        src, w = b.room, b.room.width
        joined.times[j, :w] = src.times[b.row]
        joined.poses[:, j, :w] = src.poses[:, b.row]
        joined.velocities[j, :w] = src.velocities[b.row]
    joined.counts[:n] = [len(b) for b in live]
    joined.has_velocities[:n] = [b.has_velocities for b in live]
    joined.newest[:] = joined.base + joined.counts - 1
    joined.n = n
    return joined, np.arange(len(live), dtype=np.intp), True


def _live_times(
    buffers: Sequence[StreamBuffer] | RoomBuffers, t: F64, rows: NDArray[np.intp], whole: bool
) -> F64:
    """Per-buffer playout times ``t`` cut down to the non-empty ones :func:`_rows_of` kept."""
    if t.shape != (len(buffers),):
        raise ValueError(f"Expected `t` to have shape ({len(buffers)},), got {t.shape}")
    t = t.astype(np.float64, copy=False)
    if isinstance(buffers, RoomBuffers):
        return t if whole else t[rows]
    return t[[i for i, b in enumerate(buffers) if len(b)]]


def render_buffers(
    buffers: Sequence[StreamBuffer] | RoomBuffers, t: float | F64, methods: Sequence[str]
) -> RenderFrame:
    """All non-empty buffers at playout time ``t``: one batched call per method.

    ``buffers``: a room's :class:`RoomBuffers` (every non-empty stream, in the
    order they were added: what a bot renders) or any sequence of buffers.
    ``t``: one playout time for all, or one per buffer (per row of the room, empty
    ones included), shape ``(len(buffers),)``: a stream shown late alone
    (:class:`RoomPlayoutDelay`) is rendered at its own time in the same call.
    Every stream is bracketed at once (:func:`_bracket_rows`) and the bracketing
    keyframes are gathered with one ``take`` per side; a pair method with a row
    kernel (:attr:`interp.InterpolatorInfo.rows`) runs it once on those rows.
    Window methods also see their ``lookbehind`` / ``lookahead`` keyframes either
    side of the bracket (``interp.info(m)``), gathered once for the widest
    window among ``methods``. A neighbour the buffer does not have, and every
    neighbour after a held (stalled) bracket, repeats its inward neighbour (the
    rule of :mod:`interp.registry`). Velocity methods (``needs_velocity``) see
    the bracket with its keyframes' buffered velocities; on buffers without
    velocities (``has_velocities`` false) they render :data:`VELOCITY_FALLBACK`
    instead (:func:`rendered_method`). A stall holds the bracket's keyframe for
    every kind of method.
    """
    room, rows, whole = _rows_of(buffers)
    n = rows.shape[0]
    if isinstance(t, np.ndarray):
        t = _live_times(buffers, t, rows, whole)
    if not n:
        return RenderFrame({m: np.empty((0, 7)) for m in methods}, np.zeros(0, dtype=bool))
    br = _bracket_rows(room, rows, t, whole)
    has_v = room.has_velocities[:n] if whole else room.has_velocities[rows]
    all_v = np.count_nonzero(has_v) == n
    shown = {m: rendered_method(m, all_v) for m in methods}
    entries = {name: interp_info(name) for name in dict.fromkeys([*methods, *shown.values()])}
    pair = [name for name, entry in entries.items() if entry.kind == "pair"]
    out: dict[str, NDArray[np.float64]] = {}
    if pair:
        out.update(_render_pairs(room, br, [entries[name] for name in pair]))
    rest = [name for name in entries if name not in out]
    if rest:
        out.update(_render_windows(room, br, rest, methods))
    frame = {
        m: out[m] if shown[m] == m else np.where(has_v[:, None], out[m], out[shown[m]])
        for m in methods
    }
    return RenderFrame(frame, br.stalled)


def _render_pairs(
    room: RoomBuffers, br: _Brackets, entries: list[InterpolatorInfo]
) -> dict[str, NDArray[np.float64]]:
    """Pair methods on the gathered brackets: each row kernel once (sharing what
    they have in common when there are several), plug-ins through ``f(a, b, s)``."""
    poses = room.poses.reshape(7, -1)
    a, b = poses.take(br.lo, axis=1), poses.take(br.hi, axis=1)
    n = br.lo.shape[0]
    kernels = [e.rows for e in entries if e.rows is not None]
    shared = None
    if len(kernels) > 1:
        shared = share_rows(a, b, br.s, len(SHARES_PRODUCTS.intersection(kernels)) > 1)
    out: dict[str, NDArray[np.float64]] = {}
    for entry in entries:
        if entry.rows is not None:
            # Contiguous rows to write into (faster than strided); the poses are
            # their (n, 7) transpose, a view.
            rows = np.empty((7, n))
            entry.rows(a, b, br.s, rows, None, True, shared, br.ends)
            out[entry.name] = rows.T
        else:
            out[entry.name] = entry.func(a.T, b.T, br.s)
    return out


def _render_windows(
    room: RoomBuffers, br: _Brackets, names: list[str], methods: Sequence[str]
) -> dict[str, NDArray[np.float64]]:
    """Window and velocity methods: each stream's window (before..., lo, hi, after...)
    as a ``(K, n, 7)`` track, through :func:`interp.interpolate_brackets`."""
    lb, la = window_depth(methods)
    k = lb + 2 + la
    n = br.lo.shape[0]
    slots = _window(br, lb, la)
    flat = slots.reshape(-1)
    keys = room.poses.reshape(7, -1).take(flat, axis=1).reshape(7, k, n).transpose(1, 2, 0)
    times = room.times.reshape(-1).take(flat).reshape(k, n)
    with_velocity = any(interp_info(m).needs_velocity for m in names)
    vel = (
        room.velocities.reshape(-1, 6).take(flat, axis=0).reshape(k, n, 6)
        if with_velocity
        else None
    )
    lo_idx = np.full((1, n), lb, dtype=np.intp)
    before = np.broadcast_to(np.arange(lb, dtype=np.intp)[:, None], (lb, n)).T[None]
    after = np.broadcast_to(np.arange(lb + 2, k, dtype=np.intp)[:, None], (la, n)).T[None]
    return {
        name: interpolate_brackets(
            keys,
            lo_idx,
            lo_idx + 1,
            br.s[None],
            name,
            times=times,
            velocities=vel,
            before=before,
            after=after,
        )[0]
        for name in names
    }


@dataclass(frozen=True)
class ReceivedStream:
    """A remote stream as a receiver saw it, for :func:`score_received`.

    ``label`` is the sender's motion spec (None: unknown, not scored); ``log``
    builds its arrival log, and is only called for a stream that is scored.
    """

    label: str | None
    name: str
    log: Callable[[], KeyframeLog]
    #: The D it was rendered with at each render, when not the room's (shown late).
    delays: F64 | None = None


def score_received(
    streams: Iterable[ReceivedStream],
    play_t: F64,
    play_d: F64,
    methods: Sequence[str],
    *,
    delays: Sequence[float | None] = (None,),
    until_sender_left: bool = False,
    as_rendered: bool = True,
    truths: dict[str, Trace] | None = None,
    windows: dict[str, dict[str, tuple[float, float]]] | None = None,
) -> list[dict[str, dict[str, ErrorSamples]]]:
    """QoE of what one receiver got, against each sender's motion, one result per delay.

    ``play_t``, ``play_d`` (non-empty): the render loop's playout times and the
    delay D in effect at each (a stream's own ``delays`` instead, if it has them:
    its playout times are then ``play_t + play_d - delays``). Each entry of
    ``delays`` is a fixed D in seconds, or None for the D the render loop used at
    each tau. A stream is scored over its first keyframe (or the first render) to
    its last render, or, with
    ``until_sender_left``, to its last keyframe where that is earlier (streams
    with nothing in that window are skipped). With ``as_rendered`` a velocity
    method is scored as what the render loop showed on a stream without
    velocities (:func:`rendered_method`). ``truths`` caches the motions by
    label; ``windows`` collects ``{label: {name: window}}`` of scored streams.
    Returns ``[{method: {device_class: ErrorSamples}}]``, one per delay.
    """
    pt = np.asarray(play_t)
    pd = np.asarray(play_d)

    out: list[dict[str, dict[str, ErrorSamples]]] = [{m: {} for m in methods} for _ in delays]
    truths = {} if truths is None else truths
    for rs in streams:
        if rs.label is None:
            continue
        if rs.label not in truths:
            try:
                truths[rs.label] = MotionSpec.parse(rs.label).truth(until=float(pt[-1]) + 1.0)
            except TraceError:
                continue
        truth = truths[rs.label]
        if rs.name not in truth.streams:
            continue
        log = rs.log()
        st, sd = pt, pd
        if rs.delays is not None:  # its own playout times (kept monotonic for interp)
            sd = np.asarray(rs.delays)
            st = np.maximum.accumulate(pt + pd - sd)
        end = float(st[-1])
        if until_sender_left:
            end = min(end, float(log.capture[-1]))
        window = (max(float(log.capture[0]), float(st[0])), end)
        if until_sender_left and window[1] <= window[0]:
            continue
        if windows is not None:
            windows.setdefault(rs.label, {})[rs.name] = window
        # What the render loop showed: velocity methods fall back on streams without.
        has_velocities = log.velocities is not None
        shown = {m: rendered_method(m, has_velocities) if as_rendered else m for m in methods}
        unique = list(dict.fromkeys(shown.values()))
        one = truth.select([rs.name])
        for into, fixed in zip(out, delays, strict=True):
            at = cast(Callable[[F64], F64], partial(np.interp, xp=st, fp=sd))
            res = evaluate_group(one, log, at if fixed is None else fixed, unique, window)
            for m in methods:
                for cls, samples in res[shown[m]].items():
                    into[m].setdefault(cls, ErrorSamples()).merge(samples)
    return out
