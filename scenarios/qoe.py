"""Quality of experience: the one implementation of DESIGN.md's definitions.

For each remote stream and each ground-truth sample time ``tau`` in the
evaluation window, the rendered pose is the interpolation between the keyframes
that bracket ``tau``, using only keyframes that had arrived by ``tau + D``
(``D`` = playout delay). If none bracket ``tau``, the newest arrived keyframe is
held and the sample counts as a stall. Ground truth is the source's own sample
at ``tau``.

The offline comparison, the Table 1 simulator, the live bots and replays all go
through :func:`playout_brackets` and :func:`evaluate_group`, so their numbers
mean the same thing. Nothing here reads a clock: times are arguments. The
per-class statistics (:class:`ErrorSamples`, :data:`STAT_KEYS`, the velocity
error) live in :mod:`scenarios.qoe_stats` and are re-exported here.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from posecast.interp import (
    dq_slerp,
    interpolate_brackets,
    position_error_mm,
    rotation_error_deg,
    screw_extrapolate,
    tip_error_mm,
)
from posecast.interp import (
    info as interp_info,
)
from posecast.interp.extrapolate import twist_extrapolate
from posecast.scenarios.qoe_stats import (
    EXTRAPOLATION_KEYS,
    STAT_KEYS,
    ErrorSamples,
    tip_velocity_error_mps,
)
from posecast.scenarios.traces import Trace, device_class

__all__ = [
    "CLASS_ORDER",
    "EXTRAPOLATION_KEYS",
    "MAX_REORDER_DEPTH",
    "STAT_KEYS",
    "ErrorSamples",
    "ExtrapolateMode",
    "KeyframeLog",
    "Playout",
    "Rendered",
    "StallPlan",
    "apply_stalls",
    "evaluate_group",
    "extrapolate_stalls",
    "ideal_delay",
    "ideal_log",
    "interpolate_playout",
    "plan_stalls",
    "playout_brackets",
    "render_playout",
    "sample_keyframes",
    "summarize",
    "tip_velocity_error_mps",
    "window_depth",
]

#: How far (in keyframes) the bracket search looks past keyframes that have
#: not arrived yet; deeper reordering than this is treated as a stall.
MAX_REORDER_DEPTH = 32

#: Device classes in report order. ``objects``: object streams a user publishes;
#: ``object``, ``object-flight``, ``object-catch``: a shared room object of the live
#: throw-catch scene, all of it, in flight, and around each catch
#: (:mod:`scenarios.throw_catch`).
CLASS_ORDER = ("hands", "head", "objects", "object", "object-flight", "object-catch")
F64 = NDArray[np.float64]

#: How a stalled query is dead-reckoned: ``screw`` continues the screw motion of
#: the two newest arrived keyframes; ``velocity`` moves the newest one at the
#: constant twist it was sent with (needs keyframe velocities); ``auto`` uses
#: ``velocity`` for methods that need velocities and ``screw`` for the others.
ExtrapolateMode = Literal["screw", "velocity", "auto"]


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
    themselves when none had arrived), for window interpolators; ``before``
    ``(Q, B)`` (oldest first, ``before[:, -1] == prev``) and ``after`` ``(Q, A)``
    (nearest first, ``after[:, 0] == nxt``) hold as many arrived neighbours as
    :func:`playout_brackets` was asked for, each missing one repeating its
    inward neighbour (the rule of :mod:`interp.registry`).
    """

    lo: NDArray[np.intp]
    hi: NDArray[np.intp]
    s: F64
    stall: NDArray[np.bool_]
    missing: NDArray[np.bool_]
    prev: NDArray[np.intp] | None = None
    nxt: NDArray[np.intp] | None = None
    before: NDArray[np.intp] | None = None
    after: NDArray[np.intp] | None = None


def window_depth(methods: Iterable[str]) -> tuple[int, int]:
    """Neighbours (before, after) a playout must gather for all of ``methods`` (at least 1, 1)."""
    lb, la = 1, 1
    for m in methods:
        entry = interp_info(m)
        lb, la = max(lb, entry.lookbehind), max(la, entry.lookahead)
    return lb, la


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


def ideal_log(times: F64, poses: F64, rate: float, velocities: F64 | None = None) -> KeyframeLog:
    """The keyframes a ``rate`` sender sends of a trace, each arriving as it is sent.

    ``times`` (N,) and ``poses`` (N, S, 7) are the native samples (``velocities``
    (N, S, 6) optional); the keyframes are :func:`sample_keyframes`' (an ideal
    network: arrival = send time).
    """
    send, idx = sample_keyframes(times, rate)
    return KeyframeLog(
        capture=times[idx],
        arrival=send,
        poses=poses[idx],
        velocities=None if velocities is None else velocities[idx],
    )


def ideal_delay(rate: float, native_rate: float, lookahead: int = 0) -> float:
    """One-interval playout on an ideal network (plus any look-ahead intervals).

    One send interval plus one native frame: a keyframe is captured up to one
    native frame before its send time, so this is the smallest delay at which an
    ideal link never stalls. A method that needs ``lookahead`` keyframes past
    the bracket (``interp.info(m).lookahead``) waits that many intervals more,
    so that all of them have arrived for every query inside the track.
    """
    return (1.0 + lookahead) / rate + 1.0 / native_rate


def playout_brackets(
    capture: F64,
    arrival: F64,
    query: F64,
    delay: float | F64,
    *,
    lookbehind: int = 1,
    lookahead: int = 1,
) -> Playout:
    """Bracketing keyframes for each ``tau`` among those arrived by ``tau + delay``.

    ``delay`` is one D for all queries or one per query. ``lookbehind`` /
    ``lookahead`` (at least 1 each): how many arrived neighbours of the bracket
    to gather for window interpolators (``Playout.before`` / ``after``;
    :func:`window_depth` gives what a set of methods needs). Not-yet-arrived
    keyframes are skipped; past the newest arrived one (or after a stall's held
    keyframe) a neighbour repeats its inward neighbour.
    """
    if lookbehind < 1 or lookahead < 1:
        raise ValueError(f"expected lookbehind, lookahead >= 1, got {lookbehind}, {lookahead}")
    k = capture.shape[0]
    q = np.asarray(query, dtype=np.float64)
    deadline = q + delay
    if k == 0:
        return _empty_playout(q.shape, lookbehind, lookahead)
    n = np.searchsorted(capture, q, side="right")  # first keyframe after tau
    newest = _newest_arrived(arrival, deadline)
    lo, ok_lo = _walk(n - 1, -1, arrival, deadline, k)
    hi, ok_hi = _walk(n, +1, arrival, deadline, k)
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
    cols_b, cols_a = _window_columns(
        lo_out, hi_out, bracketed, lookbehind, lookahead, arrival, deadline, k
    )
    prev, nxt = cols_b[1], cols_a[1]
    before = np.stack(cols_b[:0:-1], axis=-1).astype(np.intp)
    after = np.stack(cols_a[1:], axis=-1).astype(np.intp)
    return Playout(
        lo=lo_out.astype(np.intp),
        hi=hi_out.astype(np.intp),
        s=np.clip(s, 0.0, 1.0),
        stall=~bracketed,
        missing=newest < 0,
        prev=prev.astype(np.intp),
        nxt=nxt.astype(np.intp),
        before=before,
        after=after,
    )


def _empty_playout(shape: tuple[int, ...], lookbehind: int, lookahead: int) -> Playout:
    """No keyframes at all: every query is missing (and a stall)."""
    z = np.zeros(shape, dtype=np.intp)
    ones = np.ones(shape, dtype=bool)
    zb = np.zeros((*shape, lookbehind), dtype=np.intp)
    za = np.zeros((*shape, lookahead), dtype=np.intp)
    return Playout(z, z, np.zeros(shape), ones, ones, z, z, zb, za)


def _newest_arrived(arrival: F64, deadline: F64) -> NDArray[np.intp]:
    """Newest keyframe (in capture order) arrived by each deadline, for holds (-1: none)."""
    order = np.argsort(arrival, kind="stable")
    newest_by_arrival = np.maximum.accumulate(order)
    m = np.searchsorted(arrival[order], deadline, side="right")
    out: NDArray[np.intp] = np.where(m > 0, newest_by_arrival[np.maximum(m - 1, 0)], -1)
    return out


def _arrived(i: NDArray[np.intp], arrival: F64, deadline: F64, k: int) -> NDArray[np.bool_]:
    """Whether keyframe ``i`` (per query; may lie outside ``[0, k)``) arrived by the deadline."""
    inside = (i >= 0) & (i < k)
    out: NDArray[np.bool_] = inside & (arrival[np.clip(i, 0, k - 1)] <= deadline)
    return out


def _walk(
    i: NDArray[np.intp], step: int, arrival: F64, deadline: F64, k: int
) -> tuple[NDArray[np.intp], NDArray[np.bool_]]:
    """Move each index by ``step`` past keyframes not arrived by its deadline.

    Stops at the first arrived keyframe, or just outside ``[0, k)``;
    reordering deeper than MAX_REORDER_DEPTH counts as not arrived.
    """
    ok = _arrived(i, arrival, deadline, k)
    for _ in range(MAX_REORDER_DEPTH):
        move = ~ok & (i >= 0) & (i < k)
        if not move.any():
            break
        i = np.where(move, i + step, i)
        ok = _arrived(i, arrival, deadline, k)
    return i, ok


def _window_columns(
    lo_out: NDArray[np.intp],
    hi_out: NDArray[np.intp],
    bracketed: NDArray[np.bool_],
    lookbehind: int,
    lookahead: int,
    arrival: F64,
    deadline: F64,
    k: int,
) -> tuple[list[NDArray[np.intp]], list[NDArray[np.intp]]]:
    """Arrived neighbours of the bracket, for window interpolators.

    Each one is the next arrived keyframe outwards, or a repeat of its inward
    neighbour. Returns ``[lo, prev, ...]`` and ``[hi, nxt, ...]`` (inside out).
    """
    cols_b = [lo_out]
    for _ in range(lookbehind):
        cand, ok = _walk(cols_b[-1] - 1, -1, arrival, deadline, k)
        cols_b.append(np.where(ok, cand, cols_b[-1]))
    cols_a = [hi_out]
    for _ in range(lookahead):
        cand, ok = _walk(cols_a[-1] + 1, +1, arrival, deadline, k)
        cols_a.append(np.where(ok & bracketed, cand, cols_a[-1]))
    return cols_b, cols_a


@dataclass(frozen=True)
class Rendered:
    """What a receiver shows for each query of :func:`render_playout`.

    ``poses`` ``(Q', S, 7)`` for the ``shown`` queries (``(Q,)`` mask: not
    ``missing``), in query order. Per query ``(Q,)``: ``extrapolated`` (a stall
    rendered by dead reckoning instead of a hold), ``beyond_horizon`` (of
    those, clipped at the horizon) and ``corrected`` (inside a correction
    blend). ``events`` are the query indices where the stalled pose gives way
    to a newer one (the first frame after a keyframe arrives); ``jump_tip_mm``
    and ``jump_pos_mm`` ``(E, S)`` are the correction sizes there.
    """

    poses: F64
    shown: NDArray[np.bool_]
    extrapolated: NDArray[np.bool_]
    beyond_horizon: NDArray[np.bool_]
    corrected: NDArray[np.bool_]
    events: NDArray[np.intp]
    jump_tip_mm: F64
    jump_pos_mm: F64
    #: The same poses before any correction blend (``poses`` itself without one).
    unblended: F64 | None = None


def _stalled_poses(
    log: KeyframeLog,
    hold: NDArray[np.intp],
    prev: NDArray[np.intp],
    ext: NDArray[np.bool_],
    taus: F64,
    horizon: float,
    velocity: bool,
) -> tuple[F64, NDArray[np.bool_]]:
    """What a stall shows at ``taus``: the held keyframe, or dead reckoning from it.

    ``hold`` is the newest arrived keyframe, ``prev`` the arrived one before it
    (screw mode), ``ext`` where to extrapolate. Returns ``(n, S, 7)`` poses and
    where the horizon clipped the extrapolation.
    """
    out = log.poses[hold].copy()
    beyond = np.zeros(taus.shape, dtype=bool)
    if not ext.any():
        return out, beyond
    h, tq = hold[ext], taus[ext]
    dt = tq - log.capture[h]
    beyond[ext] = dt > horizon
    dt = np.minimum(dt, horizon)
    if velocity:
        assert log.velocities is not None
        out[ext] = twist_extrapolate(log.poses[h], log.velocities[h], dt[:, None])
    else:
        pv = prev[ext]
        span = log.capture[h] - log.capture[pv]
        s = 1.0 + dt / span
        out[ext] = screw_extrapolate(
            log.poses[pv], log.poses[h], s[:, None], max_s=float(s.max(initial=1.0))
        )
    return out, beyond


def render_playout(
    log: KeyframeLog,
    taus: F64,
    play: Playout,
    method: str,
    *,
    extrapolate_horizon: float | None = None,
    correction_time: float = 0.0,
    extrapolate_mode: ExtrapolateMode = "screw",
) -> Rendered:
    """Render ``method`` at the queries ``taus`` (increasing) given their ``play``.

    Bracketed queries are interpolated (window methods with the arrived
    neighbours, velocity methods with ``log.velocities``). A stall holds the
    newest arrived keyframe or, with ``extrapolate_horizon > 0`` (seconds past
    that keyframe's capture), dead-reckons it (``extrapolate_mode``): along the
    screw from the arrived keyframe before it (needs two arrived keyframes;
    otherwise a hold), or at the newest keyframe's own velocity; past the
    horizon the pose stays where the horizon left it. Stalls whose query lies
    before the newest keyframe (deep reordering) are held.

    A **correction event** is a frame whose predecessor was a stall and which
    shows a different source (it is now bracketed, or a newer keyframe is
    held or extrapolated). Its size is the distance between the previous
    stall's pose continued to this frame and the new pose. With
    ``correction_time > 0`` the receiver hides it: for ``correction_time``
    seconds after the event it shows ``ScLERP(old, new, w)`` with a smoothstep
    ``w`` from 0 to 1 (old = the previous stall continued, new = what the
    keyframes now give). Only the most recent event blends; an event inside an
    earlier blend starts from the unblended old pose (a small jump that a
    stateful renderer would not show).
    """
    entry = interp_info(method)
    if entry.needs_velocity and log.velocities is None:
        raise ValueError(f"{method} needs keyframes with velocities")
    if extrapolate_mode not in ("screw", "velocity", "auto"):
        raise ValueError(f"unknown extrapolate_mode {extrapolate_mode!r}")
    if extrapolate_horizon is not None and not extrapolate_horizon >= 0:
        raise ValueError(f"extrapolate_horizon must be >= 0, got {extrapolate_horizon}")
    if not correction_time >= 0:
        raise ValueError(f"correction_time must be >= 0, got {correction_time}")
    velocity = extrapolate_mode == "velocity" or (
        extrapolate_mode == "auto" and entry.needs_velocity
    )
    if velocity and log.velocities is None:
        raise ValueError("velocity extrapolation needs keyframes with velocities")
    q = taus.shape[0]
    s_count = log.poses.shape[1]
    shown = ~play.missing
    none = np.zeros(q, dtype=bool)
    empty = np.empty((0, s_count))
    if not (q and log.capture.size):
        return Rendered(
            np.empty((0, s_count, 7)), shown, none, none, none, np.empty(0, np.intp), empty, empty
        )
    assert play.prev is not None and play.nxt is not None
    poses = interpolate_playout(log, play, method, shown)
    if extrapolate_horizon is None:
        return Rendered(poses, shown, none, none, none, np.empty(0, np.intp), empty, empty)
    return extrapolate_stalls(
        log,
        taus,
        play,
        poses,
        horizon=extrapolate_horizon,
        correction_time=correction_time,
        velocity=velocity,
    )


def interpolate_playout(
    log: KeyframeLog, play: Playout, method: str, rows: NDArray[np.bool_] | None = None
) -> F64:
    """``method`` at the brackets of ``play`` (only at ``rows``, if given), ``(Q, S, 7)``."""

    def at(x: NDArray[Any]) -> NDArray[Any]:
        return x if rows is None else x[rows]

    keywords: dict[str, Any] = {"times": log.capture, "velocities": log.velocities}
    if play.before is not None and play.after is not None:
        keywords.update(before=at(play.before), after=at(play.after))
    else:
        assert play.prev is not None and play.nxt is not None
        keywords.update(prev=at(play.prev), nxt=at(play.nxt))
    return interpolate_brackets(log.poses, at(play.lo), at(play.hi), at(play.s), method, **keywords)


@dataclass(frozen=True)
class StallPlan:
    """The method-independent part of dead reckoning, for one log, playout and setting.

    What stalls show does not depend on the interpolator (only on the arrived
    keyframes), so :func:`plan_stalls` computes it once and :func:`apply_stalls`
    puts it over each method's rendering. Per query ``(Q,)``: ``stall``
    (shown stalls), ``extrapolated``, ``beyond_horizon``, ``blend``; ``row``
    maps a query to its row among the shown ones. ``stall_poses`` are the
    stalls' poses, ``events`` the correction events and ``cont`` the previous
    stall continued to each event; ``blend_old`` and ``blend_w`` the old pose
    and the weight of the new one in each blended query.
    """

    shown: NDArray[np.bool_]
    stall: NDArray[np.bool_]
    extrapolated: NDArray[np.bool_]
    beyond_horizon: NDArray[np.bool_]
    row: NDArray[np.intp]
    stall_poses: F64
    events: NDArray[np.intp]
    cont: F64
    blend: NDArray[np.bool_]
    blend_old: F64
    blend_w: F64


def plan_stalls(
    log: KeyframeLog,
    taus: F64,
    play: Playout,
    *,
    horizon: float,
    correction_time: float = 0.0,
    velocity: bool = False,
) -> StallPlan:
    """What every stall shows, the correction events and the blends (see :func:`render_playout`).

    ``horizon`` 0 means hold. ``velocity`` selects dead reckoning at the newest
    keyframe's velocity instead of along the last screw.
    """
    if not horizon >= 0 or not correction_time >= 0:
        raise ValueError("horizon and correction_time must be >= 0")
    if velocity and log.velocities is None:
        raise ValueError("velocity extrapolation needs keyframes with velocities")
    assert play.prev is not None
    q = taus.shape[0]
    shown = ~play.missing
    horizon = float(horizon)
    stall = play.stall & shown
    hold, prev = play.hi, play.prev
    ahead = taus > log.capture[hold]
    ext = stall & ahead & ((prev < hold) | velocity) & (horizon > 0)
    where = np.flatnonzero(shown)  # rendered row of each shown query
    row = np.full(q, -1, dtype=np.intp)
    row[where] = np.arange(where.size)
    st, beyond_st = _stalled_poses(
        log, hold[stall], prev[stall], ext[stall], taus[stall], horizon, velocity
    )
    beyond = np.zeros(q, dtype=bool)
    beyond[stall] = beyond_st
    # Correction events: the frame after a stall shows another source.
    before = np.r_[False, stall[:-1]]
    same = np.r_[False, stall[1:] & (hold[1:] == hold[:-1])]
    events = np.flatnonzero(before & shown & ~same)
    src = events - 1  # the stalled frame each event leaves
    cont, _ = _stalled_poses(log, hold[src], prev[src], ext[src], taus[events], horizon, velocity)
    blend = np.zeros(q, dtype=bool)
    old = np.empty((0, *log.poses.shape[1:]))
    w = np.empty(0)
    if correction_time > 0 and events.size:
        k = np.searchsorted(taus[events], taus, side="right") - 1  # latest event at or before
        age = taus - taus[events[np.maximum(k, 0)]]
        blend = shown & (k >= 0) & (age < correction_time)
        if blend.any():
            e = events[k[blend]] - 1
            old, _ = _stalled_poses(log, hold[e], prev[e], ext[e], taus[blend], horizon, velocity)
            w = age[blend] / correction_time
            w = w * w * (3.0 - 2.0 * w)
    return StallPlan(shown, stall, ext, beyond, row, st, events, cont, blend, old, w)


def apply_stalls(plan: StallPlan, base: F64) -> Rendered:
    """A method's ``base`` rendering (shown queries; stalls held) with ``plan`` put over it.

    ``base`` is not modified (without stalls the result shares it).
    """
    if not (plan.stall.any() or plan.events.size):
        empty = np.empty((0, *base.shape[1:-1]))
        return Rendered(
            base,
            plan.shown,
            plan.extrapolated,
            plan.beyond_horizon,
            plan.blend,
            plan.events,
            empty,
            empty,
            unblended=base,
        )
    poses = base.copy()
    row = plan.row
    poses[row[plan.stall]] = plan.stall_poses
    new = poses[row[plan.events]]
    jump_pos = position_error_mm(plan.cont, new)
    jump_tip = tip_error_mm(plan.cont, new)
    unblended = poses
    if plan.blend.any():
        poses = poses.copy()
        rb = row[plan.blend]
        poses[rb] = dq_slerp(plan.blend_old, poses[rb], plan.blend_w[:, None])
    return Rendered(
        poses,
        plan.shown,
        plan.extrapolated,
        plan.beyond_horizon,
        plan.blend,
        plan.events,
        jump_tip,
        jump_pos,
        unblended=unblended,
    )


def extrapolate_stalls(
    log: KeyframeLog,
    taus: F64,
    play: Playout,
    base: F64,
    *,
    horizon: float,
    correction_time: float = 0.0,
    velocity: bool = False,
) -> Rendered:
    """Dead-reckon the stalls of an already rendered ``base`` (the shown queries, held).

    The second half of :func:`render_playout` (see there): :func:`plan_stalls`
    then :func:`apply_stalls`. ``base`` is not modified.
    """
    plan = plan_stalls(
        log, taus, play, horizon=horizon, correction_time=correction_time, velocity=velocity
    )
    return apply_stalls(plan, base)


def evaluate_group(
    truth: Trace,
    log: KeyframeLog,
    delay: float | Callable[[F64], F64],
    methods: Sequence[str],
    window: tuple[float, float] | None = None,
    *,
    extrapolate_horizon: float | None = None,
    correction_time: float = 0.0,
    extrapolate_mode: ExtrapolateMode = "screw",
) -> dict[str, dict[str, ErrorSamples]]:
    """Errors of every method for one sender's streams, by device class.

    ``truth`` holds the sender's streams at their native sample times (the
    same streams, in the same order, as ``log.poses``). ``delay`` is the
    playout delay D, or a function giving the D in effect for each ``tau``
    (an adaptive receiver). Queries are the truth
    samples inside ``window`` (default: first to last keyframe capture).
    ``extrapolate_horizon`` (seconds; None = hold, the default) dead-reckons
    stalls and ``correction_time`` smooths the corrections, as in
    :func:`render_playout`; stalls are counted either way, and the
    :class:`ErrorSamples` also count extrapolated samples and correction sizes.
    Velocity errors are taken between consecutive queries that were both shown.
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
    lb, la = window_depth(methods)
    play = playout_brackets(log.capture, log.arrival, taus, d, lookbehind=lb, lookahead=la)
    shown = ~play.missing
    out: dict[str, dict[str, ErrorSamples]] = {}
    n_streams = truth.poses.shape[1]
    for name in methods:
        per_class: dict[str, ErrorSamples] = {}
        ren: Rendered | None = None
        if taus.size and log.capture.size:
            ren = render_playout(
                log,
                taus,
                play,
                name,
                extrapolate_horizon=extrapolate_horizon,
                correction_time=correction_time,
                extrapolate_mode=extrapolate_mode,
            )
            rendered = ren.poses
            ref = true_poses[shown]
            pos = position_error_mm(rendered, ref)
            rot = rotation_error_deg(rendered, ref)
            tip = tip_error_mm(rendered, ref)
            vel = tip_velocity_error_mps(rendered, true_poses, taus, shown)
        else:
            pos = rot = tip = vel = np.empty((0, n_streams))
        stalls = int(play.stall.sum())
        for j, stream in enumerate(truth.streams):
            cls = device_class(stream)
            samples = per_class.setdefault(cls, ErrorSamples())
            samples.add(pos[:, j], rot[:, j], tip[:, j], stalls, taus.size, vel=vel[:, j])
            if ren is not None and extrapolate_horizon is not None:
                samples.add_extrapolation(
                    int(ren.extrapolated.sum()),
                    int(ren.beyond_horizon.sum()),
                    ren.jump_tip_mm[:, j],
                    ren.jump_pos_mm[:, j],
                )
        out[name] = per_class
    return out


def summarize(
    groups: Iterable[dict[str, dict[str, ErrorSamples]]],
    *,
    extrapolation: bool = False,
) -> dict[str, dict[str, dict[str, float]]]:
    """Pool several groups' errors: ``{method: {class: {STAT_KEYS...}}}``.

    With ``extrapolation`` the :data:`EXTRAPOLATION_KEYS` are added.
    """
    pooled: dict[str, dict[str, ErrorSamples]] = {}
    for g in groups:
        for method, classes in g.items():
            dst = pooled.setdefault(method, {})
            for cls, samples in classes.items():
                dst.setdefault(cls, ErrorSamples()).merge(samples)
    return {
        method: {
            cls: (
                {**classes[cls].stats(), **classes[cls].extrapolation_stats()}
                if extrapolation
                else classes[cls].stats()
            )
            for cls in CLASS_ORDER
            if cls in classes
        }
        for method, classes in pooled.items()
    }
