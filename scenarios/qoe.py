"""Quality of experience: the one implementation of DESIGN.md's definitions.

For each remote stream and each ground-truth sample time ``tau`` in the
evaluation window, the rendered pose is the interpolation between the keyframes
that bracket ``tau``, using only keyframes that had arrived by ``tau + D``
(``D`` = playout delay). If none bracket ``tau``, the newest arrived keyframe is
held and the sample counts as a stall. Ground truth is the source's own sample
at ``tau``.

The offline comparison, the Table 1 simulator, the live bots and replays all go
through :func:`playout_brackets` and :func:`evaluate_group`, so their numbers
mean the same thing. Nothing here reads a clock: times are arguments.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from interp import (
    info as interp_info,
)
from interp import (
    interpolate_brackets,
    position_error_mm,
    rotation_error_deg,
    tip_error_mm,
)
from scenarios.traces import Trace, device_class

__all__ = [
    "CLASS_ORDER",
    "MAX_REORDER_DEPTH",
    "STAT_KEYS",
    "ErrorSamples",
    "KeyframeLog",
    "Playout",
    "evaluate_group",
    "ideal_delay",
    "playout_brackets",
    "sample_keyframes",
    "summarize",
]

#: How far (in keyframes) the bracket search looks past keyframes that have
#: not arrived yet; deeper reordering than this is treated as a stall.
MAX_REORDER_DEPTH = 32

CLASS_ORDER = ("hands", "head", "objects")
STAT_KEYS = (
    "pos_p50_mm",
    "pos_p95_mm",
    "rot_p50_deg",
    "rot_p95_deg",
    "tip_p50_mm",
    "tip_p95_mm",
    "stall_fraction",
)

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class KeyframeLog:
    """Keyframes of a group of streams that share capture times (one sender).

    ``capture`` (K,) strictly increasing server-clock capture times, ``arrival``
    (K,) receiver arrival times in the same clock, ``poses`` (K, S, 7).
    """

    capture: F64
    arrival: F64
    poses: F64
    #: Optional (K, S, 6) tracker velocities sent with the keyframes.
    velocities: F64 | None = None

    def __post_init__(self) -> None:
        k = self.capture.shape[0]
        if self.capture.shape != (k,) or self.arrival.shape != (k,):
            raise ValueError("expected `capture` and `arrival` to have shape (K,)")
        if self.poses.ndim != 3 or self.poses.shape[0] != k or self.poses.shape[2] != 7:
            raise ValueError(f"expected `poses` to have shape ({k}, S, 7), got {self.poses.shape}")
        if k > 1 and not np.all(np.diff(self.capture) > 0):
            raise ValueError("expected `capture` to be strictly increasing")
        if self.velocities is not None and self.velocities.shape != (*self.poses.shape[:2], 6):
            raise ValueError(
                f"expected `velocities` to have shape ({k}, S, 6), got {self.velocities.shape}"
            )


@dataclass(frozen=True)
class Playout:
    """Per query: bracket ``lo``/``hi``, fraction ``s``, ``stall`` and ``missing``.

    ``missing`` marks queries for which no keyframe had arrived at all (nothing
    to show; they count as stalls and are left out of the error statistics).
    ``prev``/``nxt`` are the arrived neighbours of the bracket (``lo``/``hi``
    themselves when none had arrived), for window interpolators.
    """

    lo: NDArray[np.intp]
    hi: NDArray[np.intp]
    s: F64
    stall: NDArray[np.bool_]
    missing: NDArray[np.bool_]
    prev: NDArray[np.intp] | None = None
    nxt: NDArray[np.intp] | None = None


def sample_keyframes(
    times: F64, rate: float, t0: float | None = None
) -> tuple[F64, NDArray[np.intp]]:
    """Send times ``t0 + k/rate`` and, for each, the latest native sample index.

    A sender samples its tracker at each send time; the keyframe is the newest
    native sample at or before it. Send times whose newest sample was already
    sent (rate above the native rate) are dropped.
    """
    if rate <= 0:
        raise ValueError(f"expected a positive rate, got {rate}")
    start = float(times[0]) if t0 is None else t0
    n = int(np.floor((float(times[-1]) - start) * rate + 1e-9)) + 1
    send = start + np.arange(n) / rate
    idx = np.searchsorted(times, send, side="right") - 1
    keep = idx >= 0
    send, idx = send[keep], idx[keep]
    first = np.ones(idx.shape, dtype=bool)
    first[1:] = idx[1:] != idx[:-1]
    return send[first], idx[first]


def ideal_delay(rate: float, native_rate: float, lookahead: int = 0) -> float:
    """One-interval playout on an ideal network (plus any look-ahead intervals).

    One send interval plus one native frame: a keyframe is captured up to one
    native frame before its send time, so this is the smallest delay at which an
    ideal link never stalls. A method that needs ``lookahead`` keyframes past
    the bracket waits that many intervals more.
    """
    return (1.0 + lookahead) / rate + 1.0 / native_rate


def playout_brackets(capture: F64, arrival: F64, query: F64, delay: float | F64) -> Playout:
    """Bracketing keyframes for each ``tau`` among those arrived by ``tau + delay``.

    ``delay`` is one D for all queries or one per query.
    """
    k = capture.shape[0]
    q = np.asarray(query, dtype=np.float64)
    deadline = q + delay
    if k == 0:
        z = np.zeros(q.shape, dtype=np.intp)
        ones = np.ones(q.shape, dtype=bool)
        return Playout(z, z, np.zeros(q.shape), ones, ones)
    n = np.searchsorted(capture, q, side="right")  # first keyframe after tau

    def arrived(i: NDArray[np.intp]) -> NDArray[np.bool_]:
        inside = (i >= 0) & (i < k)
        out: NDArray[np.bool_] = inside & (arrival[np.clip(i, 0, k - 1)] <= deadline)
        return out

    # Newest keyframe (in capture order) arrived by each deadline, for holds.
    order = np.argsort(arrival, kind="stable")
    newest_by_arrival = np.maximum.accumulate(order)
    m = np.searchsorted(arrival[order], deadline, side="right")
    newest = np.where(m > 0, newest_by_arrival[np.maximum(m - 1, 0)], -1)

    lo = n - 1
    ok_lo = arrived(lo)
    for _ in range(MAX_REORDER_DEPTH):
        step = ~ok_lo & (lo >= 0)
        if not step.any():
            break
        lo = np.where(step, lo - 1, lo)
        ok_lo = arrived(lo)
    hi = n.copy()
    ok_hi = arrived(hi)
    for _ in range(MAX_REORDER_DEPTH):
        step = ~ok_hi & (hi < k) & (hi >= 0)
        if not step.any():
            break
        hi = np.where(step, hi + 1, hi)
        ok_hi = arrived(hi)
    lo_c = np.clip(lo, 0, k - 1)
    # A query exactly on an arrived keyframe needs no second keyframe.
    exact = ok_lo & (capture[lo_c] == q)
    bracketed = ok_lo & (ok_hi | exact)
    hi = np.where(exact | ~bracketed, lo, hi)
    hold = np.clip(newest, 0, k - 1)
    lo_out = np.where(bracketed, lo_c, hold)
    hi_out = np.where(bracketed, np.clip(hi, 0, k - 1), hold)
    span = capture[hi_out] - capture[lo_out]
    s = np.where(span > 0, (q - capture[lo_out]) / np.where(span > 0, span, 1.0), 0.0)
    # Arrived neighbours: step outwards past keyframes that had not arrived.
    prev = lo_out - 1
    ok = arrived(prev)
    for _ in range(MAX_REORDER_DEPTH):
        step = ~ok & (prev >= 0)
        if not step.any():
            break
        prev = np.where(step, prev - 1, prev)
        ok = arrived(prev)
    prev = np.where(ok, prev, lo_out)
    nxt = hi_out + 1
    ok = arrived(nxt)
    for _ in range(MAX_REORDER_DEPTH):
        step = ~ok & (nxt < k)
        if not step.any():
            break
        nxt = np.where(step, nxt + 1, nxt)
        ok = arrived(nxt)
    nxt = np.where(ok & bracketed, nxt, hi_out)
    return Playout(
        lo=lo_out.astype(np.intp),
        hi=hi_out.astype(np.intp),
        s=np.clip(s, 0.0, 1.0),
        stall=~bracketed,
        missing=newest < 0,
        prev=prev.astype(np.intp),
        nxt=nxt.astype(np.intp),
    )


@dataclass
class ErrorSamples:
    """Per-sample errors pooled over streams of one device class."""

    pos_mm: list[F64] = field(default_factory=list)
    rot_deg: list[F64] = field(default_factory=list)
    tip_mm: list[F64] = field(default_factory=list)
    stalls: int = 0
    samples: int = 0

    def add(self, pos: F64, rot: F64, tip: F64, stalls: int, samples: int) -> None:
        self.pos_mm.append(pos)
        self.rot_deg.append(rot)
        self.tip_mm.append(tip)
        self.stalls += stalls
        self.samples += samples

    def merge(self, other: ErrorSamples) -> None:
        self.pos_mm += other.pos_mm
        self.rot_deg += other.rot_deg
        self.tip_mm += other.tip_mm
        self.stalls += other.stalls
        self.samples += other.samples

    def stats(self) -> dict[str, float]:
        """p50/p95 of each error and the stall fraction (NaN where no samples)."""

        def pct(parts: list[F64], p: float) -> float:
            arr = np.concatenate(parts) if parts else np.empty(0)
            return float(np.percentile(arr, p)) if arr.size else float("nan")

        return {
            "pos_p50_mm": pct(self.pos_mm, 50),
            "pos_p95_mm": pct(self.pos_mm, 95),
            "rot_p50_deg": pct(self.rot_deg, 50),
            "rot_p95_deg": pct(self.rot_deg, 95),
            "tip_p50_mm": pct(self.tip_mm, 50),
            "tip_p95_mm": pct(self.tip_mm, 95),
            "stall_fraction": self.stalls / self.samples if self.samples else float("nan"),
        }


def evaluate_group(
    truth: Trace,
    log: KeyframeLog,
    delay: float | Callable[[F64], F64],
    methods: Sequence[str],
    window: tuple[float, float] | None = None,
) -> dict[str, dict[str, ErrorSamples]]:
    """Errors of every method for one sender's streams, by device class.

    ``truth`` holds the sender's streams at their native sample times (the
    same streams, in the same order, as ``log.poses``). ``delay`` is the
    playout delay D, or a function giving the D in effect for each ``tau``
    (an adaptive receiver). Queries are the truth
    samples inside ``window`` (default: first to last keyframe capture).
    Returns ``{method: {device_class: ErrorSamples}}``.
    """
    if truth.poses.shape[1] != log.poses.shape[1]:
        raise ValueError(
            f"truth has {truth.poses.shape[1]} streams, keyframes have {log.poses.shape[1]}"
        )
    if window is None:
        window = (float(log.capture[0]), float(log.capture[-1])) if log.capture.size else (0, -1)
    m = (truth.times >= window[0]) & (truth.times <= window[1])
    taus = truth.times[m]
    true_poses = truth.poses[m]
    d = delay(taus) if callable(delay) else delay
    play = playout_brackets(log.capture, log.arrival, taus, d)
    shown = ~play.missing
    out: dict[str, dict[str, ErrorSamples]] = {}
    for name in methods:
        per_class: dict[str, ErrorSamples] = {}
        if taus.size and log.capture.size:
            entry = interp_info(name)
            if entry.needs_velocity and log.velocities is None:
                raise ValueError(f"{name} needs keyframes with velocities")
            assert play.prev is not None and play.nxt is not None
            rendered = interpolate_brackets(
                log.poses,
                play.lo[shown],
                play.hi[shown],
                play.s[shown],
                name,
                times=log.capture,
                prev=play.prev[shown],
                nxt=play.nxt[shown],
                velocities=log.velocities,
            )
            ref = true_poses[shown]
            pos = position_error_mm(rendered, ref)
            rot = rotation_error_deg(rendered, ref)
            tip = tip_error_mm(rendered, ref)
        else:
            pos = rot = tip = np.empty((0, truth.poses.shape[1]))
        stalls = int(play.stall.sum())
        for j, stream in enumerate(truth.streams):
            cls = device_class(stream)
            per_class.setdefault(cls, ErrorSamples()).add(
                pos[:, j], rot[:, j], tip[:, j], stalls, taus.size
            )
        out[name] = per_class
    return out


def summarize(
    groups: Iterable[dict[str, dict[str, ErrorSamples]]],
) -> dict[str, dict[str, dict[str, float]]]:
    """Pool several groups' errors: ``{method: {class: {STAT_KEYS...}}}``."""
    pooled: dict[str, dict[str, ErrorSamples]] = {}
    for g in groups:
        for method, classes in g.items():
            dst = pooled.setdefault(method, {})
            for cls, samples in classes.items():
                dst.setdefault(cls, ErrorSamples()).merge(samples)
    return {
        method: {cls: classes[cls].stats() for cls in CLASS_ORDER if cls in classes}
        for method, classes in pooled.items()
    }
