"""The receiver model: clock offset, jitter buffers, adaptive playout delay.

Shared by the live bots and the offline simulator; nothing here reads a clock
(every method takes the time it needs).

- :class:`ClockEstimator`: NTP-style offset to the server clock from ping/pong
  samples, keeping the lowest round trip of a sliding window.
- :class:`StreamBuffer`: one remote stream's keyframes ordered by capture time,
  each with the velocity it came with (zeros without one); duplicates and
  stale frames dropped; bounded (oldest evicted).
- :class:`PlayoutDelay`: delay D that starts at one interval plus the measured
  arrival jitter and follows the observed keyframe age (Mirror-style dynamic
  buffer: ``D = interval + p95(age)``), slewing smoothly, never jumping.
- :func:`render_buffers`: every buffer at its playout time in one batched
  interpolator call per method, pair, window and velocity methods alike.
"""

from __future__ import annotations

import bisect
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from interp import info as interp_info
from interp import interpolate_brackets
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


class StreamBuffer:
    """Keyframes of one remote stream, by capture time, for rendering.

    ``push`` refuses duplicates (same capture time) and stale keyframes: ones
    that can never be a bracket again because a newer keyframe already sits at
    or before ``floor`` (the playout time already passed), or that are older than
    everything kept in a full buffer. A late keyframe just before the playout
    time is kept: it is the lower bracket. Beyond ``capacity`` the oldest is
    evicted.

    ``velocities[i]`` is the velocity ``(6,)`` (linear m/s, angular rad/s, world
    frame) that came with ``times[i]``/``poses[i]``, for velocity interpolators;
    a keyframe pushed without one gets zeros. ``has_velocities`` says whether the
    sender reports velocities at all: if not, the zeros are fillers, not data,
    and velocity methods render the stream with :data:`VELOCITY_FALLBACK`.
    """

    def __init__(
        self, capacity: int = DEFAULT_BUFFER_CAPACITY, *, has_velocities: bool = True
    ) -> None:
        self.capacity = capacity
        self.has_velocities = has_velocities
        self.times: list[float] = []
        self.poses: list[NDArray[np.float32]] = []
        self.velocities: list[NDArray[np.float64]] = []
        self.duplicates = 0
        self.stale = 0
        self.evicted = 0

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
        times.insert(i, capture)
        self.poses.insert(i, pose)
        self.velocities.insert(i, _NO_VELOCITY if velocity is None else velocity)
        if len(times) > self.capacity:
            del times[0]
            del self.poses[0]
            del self.velocities[0]
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
    _ages: deque[float] = field(default_factory=deque)
    _last: float | None = None

    def __post_init__(self) -> None:
        self.value = self.interval + self.margin

    def observe(self, age: float) -> None:
        """One keyframe's age on arrival (arrival minus capture, server clock)."""
        self._ages.append(age)
        while len(self._ages) > self.window:
            self._ages.popleft()

    @property
    def target(self) -> float:
        if not self._ages:
            return self.interval + self.margin
        return self.interval + float(np.percentile(self._ages, self.percentile)) + self.margin

    def update(self, now: float) -> float:
        """Slew towards the target; the first observation sets D directly."""
        target = self.target
        if self._last is None:
            if self._ages:
                self.value = target
                self._last = now
            return self.value
        dt = max(0.0, now - self._last)
        self._last = now
        self.value += (target - self.value) * min(1.0, dt / self.tau)
        return self.value


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


def render_buffers(
    buffers: Sequence[StreamBuffer], t: float, methods: Sequence[str]
) -> RenderFrame:
    """All non-empty buffers at playout time ``t``: one batched call per method.

    Pair methods see the bracket; window methods also their ``lookbehind`` /
    ``lookahead`` keyframes either side of it (``interp.info(m)``), gathered once
    for the widest window among ``methods``. A neighbour the buffer does not
    have, and every neighbour after a held (stalled) bracket, repeats its inward
    neighbour (the rule of :mod:`interp.registry`). Velocity methods
    (``needs_velocity``) see the bracket with its keyframes' buffered
    velocities; on buffers without velocities (``has_velocities`` false) they
    render :data:`VELOCITY_FALLBACK` instead (:func:`rendered_method`). A stall
    holds the bracket's keyframe for every kind of method.
    """
    live = [b for b in buffers if len(b)]
    n = len(live)
    if not n:
        return RenderFrame({m: np.empty((0, 7)) for m in methods}, np.zeros(0, dtype=bool))
    lb, la = window_depth(methods)
    with_velocity = any(interp_info(m).needs_velocity for m in methods)
    # Each stream's window (before..., lo, hi, after...) as a (K, n, 7) track,
    # converted from the buffers' float32 poses in one call.
    k = lb + 2 + la
    flat_poses: list[NDArray[np.float32]] = []
    flat_times: list[float] = []
    flat_vels: list[NDArray[np.float64]] = []
    s = np.empty((1, n))
    stalled = np.zeros(n, dtype=bool)
    for j, buf in enumerate(live):
        lo, hi, frac, stall = buf.bracket(t)
        last = len(buf) - 1
        rows = [max(lo - i, 0) for i in range(lb, 0, -1)]
        rows += [lo, hi]
        rows += [min(hi + i, last) if hi > lo else hi for i in range(1, la + 1)]
        poses, times_j = buf.poses, buf.times
        flat_poses += [poses[i] for i in rows]
        flat_times += [times_j[i] for i in rows]
        if with_velocity:
            vels = buf.velocities
            flat_vels += [vels[i] for i in rows]
        s[0, j] = frac
        stalled[j] = stall
    keys = np.array(flat_poses, dtype=np.float64).reshape(n, k, 7).transpose(1, 0, 2)
    times = np.array(flat_times, dtype=np.float64).reshape(n, k).T
    vel = (
        np.array(flat_vels, dtype=np.float64).reshape(n, k, 6).transpose(1, 0, 2)
        if with_velocity
        else None
    )
    lo_idx = np.full((1, n), lb, dtype=np.intp)
    before = np.broadcast_to(np.arange(lb, dtype=np.intp)[:, None], (lb, n)).T[None]
    after = np.broadcast_to(np.arange(lb + 2, k, dtype=np.intp)[:, None], (la, n)).T[None]
    # A velocity method shows its fallback on the rows whose sender reports no velocities.
    no_velocity = np.array([not b.has_velocities for b in live])
    shown = {m: rendered_method(m, not no_velocity.any()) for m in methods}
    out = {
        name: interpolate_brackets(
            keys,
            lo_idx,
            lo_idx + 1,
            s,
            name,
            times=times,
            velocities=vel,
            before=before,
            after=after,
        )[0]
        for name in dict.fromkeys([*methods, *shown.values()])
    }
    frame = {
        m: out[m] if shown[m] == m else np.where(no_velocity[:, None], out[shown[m]], out[m])
        for m in methods
    }
    return RenderFrame(frame, stalled)


@dataclass(frozen=True)
class ReceivedStream:
    """A remote stream as a receiver saw it, for :func:`score_received`.

    ``label`` is the sender's motion spec (None: unknown, not scored); ``log``
    builds its arrival log, and is only called for a stream that is scored.
    """

    label: str | None
    name: str
    log: Callable[[], KeyframeLog]


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
    delay D in effect at each. Each entry of ``delays`` is a fixed D in seconds,
    or None for the D the render loop used at each tau. A stream is scored over
    its first keyframe (or the first render) to the last render, or, with
    ``until_sender_left``, to its last keyframe where that is earlier (streams
    with nothing in that window are skipped). With ``as_rendered`` a velocity
    method is scored as what the render loop showed on a stream without
    velocities (:func:`rendered_method`). ``truths`` caches the motions by
    label; ``windows`` collects ``{label: {name: window}}`` of scored streams.
    Returns ``[{method: {device_class: ErrorSamples}}]``, one per delay.
    """
    pt = np.asarray(play_t)
    pd = np.asarray(play_d)

    def delay_at(taus: F64) -> F64:
        d: F64 = np.interp(taus, pt, pd)
        return d

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
        end = float(pt[-1])
        if until_sender_left:
            end = min(end, float(log.capture[-1]))
        window = (max(float(log.capture[0]), float(pt[0])), end)
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
            res = evaluate_group(one, log, delay_at if fixed is None else fixed, unique, window)
            for m in methods:
                for cls, samples in res[shown[m]].items():
                    into[m].setdefault(cls, ErrorSamples()).merge(samples)
    return out
