"""Keyframe-track evaluation: query times to bracketing keyframes to poses.

The receiver's render step and every offline QoE computation go through
:func:`evaluate_track`: keyframes at times ``(K,)`` for ``S`` streams
``(K, S, 7)``, queries ``(Q,)``; one ``searchsorted`` finds the brackets and one
batched interpolator call renders every stream at every query. Window methods
get ``lookbehind + 2 + lookahead`` keyframes per query, whatever their
window size (:func:`window_indices`; missing neighbours as in
:mod:`interp.registry`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from posecast.interp.pose import F64, as_pose
from posecast.interp.registry import Interpolator, info

__all__ = [
    "Brackets",
    "TrackResult",
    "bracket",
    "evaluate_track",
    "interpolate_brackets",
    "window_indices",
]


@dataclass(frozen=True, slots=True)
class Brackets:
    """For each query: keyframe indices ``lo``/``hi``, fraction ``s``, and ``held``.

    ``held`` marks queries outside ``[times[0], times[-1]]``: they show the
    nearest keyframe (``lo == hi``, ``s == 0``).
    """

    lo: NDArray[np.intp]
    hi: NDArray[np.intp]
    s: F64
    held: NDArray[np.bool_]


@dataclass(frozen=True, slots=True)
class TrackResult:
    """Rendered poses ``(Q, S, 7)`` and which queries were held, ``(Q,)``."""

    poses: F64
    held: NDArray[np.bool_]


def bracket(times: ArrayLike, query: ArrayLike) -> Brackets:
    """Bracketing keyframes for each query time (``times`` strictly increasing)."""
    t = np.asarray(times, dtype=np.float64)
    q = np.asarray(query, dtype=np.float64)
    if t.ndim != 1 or t.shape[0] == 0:
        raise ValueError(f"expected `times` to have shape (K,) with K >= 1, got {t.shape}")
    if q.ndim != 1:
        raise ValueError(f"expected `query` to have shape (Q,), got {q.shape}")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(q))):
        raise ValueError("expected `times` and `query` to hold finite values")
    if t.shape[0] > 1 and not np.all(np.diff(t) > 0):
        raise ValueError("expected `times` to be strictly increasing")
    k = t.shape[0]
    # hi = first keyframe strictly after q; a query exactly on the last keyframe
    # is inside the track (it reproduces that keyframe).
    hi = np.searchsorted(t, q, side="right")
    lo = hi - 1
    before = lo < 0
    after = hi >= k
    on_last = after & (q == t[-1])
    held = before | (after & ~on_last)
    lo = np.clip(lo, 0, k - 1)
    hi = np.clip(hi, 0, k - 1)
    hi = np.where(before, 0, hi)
    lo = np.where(on_last, k - 1, lo)
    span = t[hi] - t[lo]
    s = np.where(span > 0, (q - t[lo]) / np.where(span > 0, span, 1.0), 0.0)
    s = np.clip(s, 0.0, 1.0)
    return Brackets(lo=lo, hi=hi, s=s, held=held)


def evaluate_track(
    times: ArrayLike,
    poses: ArrayLike,
    query: ArrayLike,
    method: str | Interpolator = "soa",
    velocities: ArrayLike | None = None,
) -> TrackResult:
    """Render ``S`` streams at ``Q`` query times from ``K`` shared keyframes.

    ``poses`` is ``(K, S, 7)`` (or ``(K, 7)`` for one stream, returning
    ``(Q, 1, 7)``); ``method`` is a registered name or a pair interpolator
    callable; window methods use the neighbouring keyframes, velocity methods
    need ``velocities (K, S, 6)``.
    """
    p = as_pose(poses, "poses")
    if p.ndim == 2:
        p = p[:, None, :]
    if p.ndim != 3:
        raise ValueError(f"expected `poses` to have shape (K, S, 7), got {p.shape}")
    t = np.asarray(times, dtype=np.float64)
    if t.shape != (p.shape[0],):
        raise ValueError(f"expected `times` to have shape ({p.shape[0]},), got {t.shape}")
    br = bracket(t, query)
    return TrackResult(
        poses=interpolate_brackets(p, br.lo, br.hi, br.s, method, times=t, velocities=velocities),
        held=br.held,
    )


def window_indices(
    lo: ArrayLike, hi: ArrayLike, n_keys: int, lookbehind: int, lookahead: int
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Neighbours of each bracket in a track of ``n_keys`` keyframes (every one present).

    Returns ``before`` (``lo.shape + (lookbehind,)``, oldest first) and ``after``
    (``hi.shape + (lookahead,)``, nearest first): ``lo - j`` and ``hi + j``; past
    either end of the track, and after a held bracket (``lo == hi``), an entry
    repeats its inward neighbour (the rule of :mod:`interp.registry`).
    """
    lo_a = np.asarray(lo, dtype=np.intp)
    hi_a = np.asarray(hi, dtype=np.intp)
    steps_b = np.arange(lookbehind, 0, -1, dtype=np.intp)
    steps_a = np.arange(1, lookahead + 1, dtype=np.intp)
    before = np.maximum(lo_a[..., None] - steps_b, 0)
    after = np.minimum(hi_a[..., None] + steps_a, n_keys - 1)
    after = np.where((hi_a > lo_a)[..., None], after, hi_a[..., None])
    return before.astype(np.intp), after.astype(np.intp)


def _neighbours(
    given: ArrayLike | None,
    single: ArrayLike | None,
    need: int,
    default: NDArray[np.intp],
    side: str,
    method: object,
) -> NDArray[np.intp]:
    """The ``need`` neighbours on one side: ``before``/``after``, ``prev``/``nxt`` or defaults."""
    if given is not None:
        g = np.asarray(given, dtype=np.intp)
        if g.ndim != default.ndim or g.shape[:-1] != default.shape[:-1] or g.shape[-1] < need:
            raise ValueError(
                f"interpolator {method!r} needs {need} keyframe(s) {side} the bracket: expected "
                f"`{side}` of shape {(*default.shape[:-1], need)} or wider, got {g.shape}"
            )
        # The nearest ``need``: before is oldest first, after nearest first.
        return g[..., g.shape[-1] - need :] if side == "before" else g[..., :need]
    if single is not None:
        if need > 1:
            name = "prev" if side == "before" else "nxt"
            raise ValueError(
                f"interpolator {method!r} needs {need} keyframes {side} the bracket; "
                f"`{name}` gives one: pass `{side}` instead"
            )
        one = np.asarray(single, dtype=np.intp)
        return one[..., None][..., :need]
    return default


def _render_window(
    f: Callable[..., F64],
    p: F64,
    t2: F64,
    lo_a: NDArray[np.intp],
    hi_a: NDArray[np.intp],
    s_a: F64,
    cols: NDArray[np.intp],
    depth: tuple[int, int],
    given: tuple[ArrayLike | None, ArrayLike | None, ArrayLike | None, ArrayLike | None],
    method: object,
) -> F64:
    """A window method's render: gather each bracket's ``lookbehind + 2 + lookahead`` keys.

    ``t2`` is the keyframe times ``(K, S)``, ``s_a`` the fractions ``(Q, S)``, ``cols``
    the stream indices ``(S,)``, ``depth`` ``(lookbehind, lookahead)`` and ``given``
    the caller's ``(before, after, prev, nxt)`` neighbours (see
    :func:`interpolate_brackets`).
    """
    lb, la = depth
    before, after, prev, nxt = given
    k = p.shape[0]
    d_before, d_after = window_indices(lo_a, hi_a, k, lb, la)
    bw = _neighbours(before, prev, lb, d_before, "before", method)
    aw = _neighbours(after, nxt, la, d_after, "after", method)
    win = np.concatenate([bw, lo_a[..., None], hi_a[..., None], aw], axis=-1)
    if win.size and (int(win.min()) < 0 or int(win.max()) >= k):
        raise ValueError(f"expected window keyframe indices in [0, {k}), got {win.min()}..")
    if lo_a.ndim == 2:  # one bracket per stream
        keys = p[win, cols[:, None]]  # (Q, S, K', 7)
        ktimes = t2[win, cols[:, None]]
    else:
        keys = np.moveaxis(p[win], 2, 1)  # (Q, K', S, 7) -> (Q, S, K', 7)
        ktimes = np.moveaxis(t2[win], 2, 1)
    t_lo, t_hi = ktimes[..., lb], ktimes[..., lb + 1]
    return f(keys, ktimes, t_lo + s_a * (t_hi - t_lo))


def interpolate_brackets(
    poses: ArrayLike,
    lo: ArrayLike,
    hi: ArrayLike,
    s: ArrayLike,
    method: str | Interpolator = "soa",
    *,
    times: ArrayLike | None = None,
    prev: ArrayLike | None = None,
    nxt: ArrayLike | None = None,
    velocities: ArrayLike | None = None,
    before: ArrayLike | None = None,
    after: ArrayLike | None = None,
) -> F64:
    """Render keyframes ``poses (K, S, 7)`` at given brackets in one batched call.

    ``lo``, ``hi``, ``s`` have shape ``(Q,)`` (shared by all streams) or ``(Q, S)``
    (one bracket per stream); returns ``(Q, S, 7)``. Window methods also need
    ``times`` (``(K,)`` or ``(K, S)``) and their neighbours: ``before``
    (``lo.shape + (B,)``, oldest first) and ``after`` (``hi.shape + (A,)``,
    nearest first), of which the method uses the nearest ``lookbehind`` /
    ``lookahead`` (``B``, ``A`` may be larger); ``prev``/``nxt`` (shape of ``lo``)
    are the one-neighbour shorthand. Missing neighbours repeat their inward
    neighbour (see :mod:`interp.registry`); without any of these the neighbours
    are the adjacent keyframes (:func:`window_indices`). Velocity methods need
    ``velocities (K, S, 6)`` and ``times``.
    """
    p = np.asarray(poses, dtype=np.float64)
    if p.ndim != 3 or p.shape[-1] != 7:
        raise ValueError(f"expected `poses` to have shape (K, S, 7), got {p.shape}")
    lo_a = np.asarray(lo, dtype=np.intp)
    hi_a = np.asarray(hi, dtype=np.intp)
    s_a = np.asarray(s, dtype=np.float64)
    if isinstance(method, str):
        entry = info(method)
        f, kind = entry.func, entry.kind
        lb, la = entry.lookbehind, entry.lookahead
    else:
        f, kind, lb, la = method, "pair", 0, 0
    per_stream = lo_a.ndim == 2
    cols = np.arange(p.shape[1])

    def take(x: NDArray[Any], idx: NDArray[np.intp]) -> NDArray[Any]:
        """Rows ``idx`` of a (K, S, ...) array: (Q, S, ...)."""
        return x[idx, cols] if per_stream else x[idx]

    if kind == "pair":
        return f(take(p, lo_a), take(p, hi_a), s_a if per_stream else s_a[:, None])
    if not per_stream:
        s_a = np.broadcast_to(s_a[:, None], (s_a.shape[0], p.shape[1]))
    if times is None:
        raise ValueError(f"interpolator {method!r} needs keyframe `times`")
    t = np.asarray(times, dtype=np.float64)
    t2 = np.broadcast_to(t[:, None], p.shape[:2]) if t.ndim == 1 else t
    if kind == "window":
        return _render_window(
            f, p, t2, lo_a, hi_a, s_a, cols, (lb, la), (before, after, prev, nxt), method
        )
    t_lo, t_hi = take(t2, lo_a), take(t2, hi_a)
    if velocities is None:
        raise ValueError(f"interpolator {method!r} needs keyframe `velocities`")
    v = np.asarray(velocities, dtype=np.float64)
    span = t_hi - t_lo
    held = span <= 0
    return f(
        take(p, lo_a),
        take(p, hi_a),
        take(v, lo_a),
        take(v, hi_a),
        np.where(held, 1.0, span),
        np.where(held, 0.0, s_a),
    )
