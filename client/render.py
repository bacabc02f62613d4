"""Render every remote stream at its playout time: one batched call per method.

- :func:`render_buffers`: every buffer at its playout time: one vectorised
  bracket of all streams, one gather, one batched interpolator call per
  method (a pair method's allocation-free row kernel), window and velocity
  methods alike. The buffers are :class:`client.buffers.RoomBuffers` rows.
  Where the compiled render kernels are built (:mod:`interp.accel`), the
  bracket and the pair methods are one call each (the same results to float
  rounding); numpy otherwise, and with ``POSECAST_PURE=1``.
- :func:`rendered_method`: the method that actually renders a stream (a velocity
  method falls back to :data:`VELOCITY_FALLBACK` on a stream without velocities).

Sans I/O: nothing here reads a clock, a file or a socket.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from dataclasses import dataclass
from types import ModuleType
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from posecast.client.buffers import RoomBuffers, StreamBuffer
from posecast.interp import InterpolatorInfo, accel, interpolate_brackets
from posecast.interp import info as interp_info
from posecast.interp.kernels import COMPILED_KIND, SHARES_PRODUCTS, share_rows
from posecast.interp.registry import generation as registry_generation
from posecast.scenarios.qoe import window_depth

__all__ = ["VELOCITY_FALLBACK", "RenderFrame", "render_buffers", "rendered_method"]

F64 = NDArray[np.float64]

_count = np.count_nonzero
_copyto = np.copyto
_local = threading.local()


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
    v = room.whole()
    if whole:
        times, base, base_m1, newest = v.times, v.base, v.base_m1, v.newest
    else:
        times, base, newest = room.times[rows], room.base[rows], room.newest[rows]
        base_m1 = base - 1
    tt: F64 | np.float64
    if isinstance(t, np.ndarray):
        tt, due = t, times <= t[:, None]
    else:
        tt = np.float64(t)
        due = times <= tt
    after = due.argmin(axis=1)  # slot of the first keyframe after t
    lo = base_m1 + after
    if _count(after) < n:  # nothing at or before t: hold the newest
        np.copyto(lo, newest, where=after == 0)
    flat = v.flat_times
    t_lo = flat.take(lo)
    on = t_lo == tt  # exactly on a keyframe: show it, not a stall
    # Past the newest and not on it is a stall (before the first too: lo is the newest).
    at_end = lo == newest
    held = at_end | on
    stalled = np.greater(at_end, on)
    hi = lo + 1
    any_held = _count(held)
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
    ends = bool(any_held) or bool(_count(s == 1.0))
    return _Brackets(lo, hi, base, newest, s, stalled, ends)


def _bracket_c(
    ck: ModuleType, room: RoomBuffers, rows: NDArray[np.intp], t: float | F64, whole: bool
) -> _Brackets:
    """:func:`_bracket_rows` in one call of the compiled kernels (the same brackets)."""
    n = rows.shape[0]
    v = room.whole()
    if whole:
        base, newest = v.base, v.newest
    else:
        base, newest = room.base[rows], room.newest[rows]
    lo, hi, s = _bracket_scratch(n)
    stalled = np.empty(n, dtype=bool)  # the frame's own
    ends = ck.bracket_rows(v.flat_times, base, newest, t, lo, hi, s, stalled)
    return _Brackets(lo, hi, base, newest, s, stalled, ends)


def _bracket_scratch(n: int) -> tuple[NDArray[np.intp], NDArray[np.intp], F64]:
    """This thread's ``lo``, ``hi`` and ``s`` for ``n`` brackets (kept for the last ``n``)."""
    got: tuple[NDArray[np.intp], NDArray[np.intp], F64] | None = getattr(_local, "br", None)
    if got is None or got[2].shape[0] != n:
        got = _local.br = (np.empty(n, dtype=np.intp), np.empty(n, dtype=np.intp), np.empty(n))
    return got


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
        v = buffers.whole()
        if _count(v.counts) == v.n:
            return buffers, v.rows, True
        return buffers, np.flatnonzero(v.counts), False
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
        joined.pose_rows[j, :w] = src.pose_rows[b.row]
        joined.velocities[j, :w] = src.velocities[b.row]
    joined.counts[:n] = [len(b) for b in live]
    joined.has_velocities[:n] = [b.has_velocities for b in live]
    joined.newest[:] = joined.base + joined.counts - 1
    joined.n = joined.filled = n
    return joined, np.arange(len(live), dtype=np.intp), True


def _live_times(
    buffers: Sequence[StreamBuffer] | RoomBuffers, t: F64, rows: NDArray[np.intp], whole: bool
) -> F64:
    """Per-buffer playout times ``t`` cut down to the non-empty ones :func:`_rows_of` kept."""
    if t.shape != (len(buffers),):
        raise ValueError(f"Expected `t` to have shape ({len(buffers)},), got {t.shape}")
    t = np.ascontiguousarray(t, dtype=np.float64)
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
    ck = accel.kernels
    if ck is not None and isinstance(buffers, RoomBuffers):
        fast = _render_room_c(ck, buffers, t, methods)
        if fast is not None:
            return fast
    room, rows, whole = _rows_of(buffers)
    n = rows.shape[0]
    if isinstance(t, np.ndarray):
        t = _live_times(buffers, t, rows, whole)
    if not n:
        return RenderFrame({m: np.empty((0, 7)) for m in methods}, np.zeros(0, dtype=bool))
    br = _bracket_rows(room, rows, t, whole) if ck is None else _bracket_c(ck, room, rows, t, whole)
    has_v = room.whole().has_velocities if whole else room.has_velocities[rows]
    plan = _plan(methods, _count(has_v) == n)
    out: dict[str, NDArray[np.float64]] = {}
    if plan.pair:
        if ck is None or not plan.compiled:
            out.update(_render_pairs(room, br, plan.pair, plan.share))
        else:
            out.update(_render_pairs_c(ck, room, br, plan.pair))
    if plan.rest:
        out.update(_render_windows(room, br, plan.rest, methods))
    if plan.direct:
        return RenderFrame(out, br.stalled)
    shown = plan.shown
    frame = {
        m: out[m] if shown[m] == m else np.where(has_v[:, None], out[m], out[shown[m]])
        for m in methods
    }
    return RenderFrame(frame, br.stalled)


class _Plan(NamedTuple):
    """What a frame of ``methods`` renders, looked up once (:func:`_plan`)."""

    generation: tuple[int, int]
    #: Each method and the one that renders it (:func:`rendered_method`).
    shown: dict[str, str]
    #: Pair methods' entries, then the other methods' names, to run (each once).
    pair: list[InterpolatorInfo]
    rest: list[str]
    #: What the row kernels share (:func:`interp.kernels.share_rows`): nothing (None,
    #: fewer than two kernels), the alignment (False) or also the products (True).
    share: bool | None
    #: Whether every method renders itself and what runs is ``methods`` in order
    #: (then the frame is what ran).
    direct: bool
    #: Whether every pair method has a compiled kernel (:data:`COMPILED_KIND`), and
    #: their numbers (the pair methods in order).
    compiled: bool
    kinds: tuple[int, ...]
    #: The pair methods' names, in order.
    names: tuple[str, ...]


_plans: dict[tuple[tuple[str, ...], bool], _Plan] = {}


def _plan(methods: Sequence[str], all_v: bool) -> _Plan:
    """The plan for ``methods`` when all streams have velocities (``all_v``) or not,
    kept until the interpolator registry changes."""
    gen = registry_generation()
    last = _last_plan
    if last is not None and last[0] is methods and last[1] == all_v and last[2].generation == gen:
        return last[2]  # a render loop's frames: the same methods object each time
    key = (tuple(methods), all_v)
    plan = _plans.get(key)
    if plan is not None and plan.generation == gen:
        return _remember(methods, all_v, plan)
    shown = {m: rendered_method(m, all_v) for m in methods}
    entries = {name: interp_info(name) for name in dict.fromkeys([*methods, *shown.values()])}
    pair = [e for e in entries.values() if e.kind == "pair"]
    rest = [name for name, e in entries.items() if e.kind != "pair"]
    order = [e.name for e in pair] + rest
    direct = order == list(methods) and all(shown[m] == m for m in methods)
    kernels = [e.rows for e in pair if e.rows is not None]
    share = None if len(kernels) < 2 else len(SHARES_PRODUCTS.intersection(kernels)) > 1
    if len(_plans) >= 64:  # a bounded cache: callers use a handful of method sets
        _plans.clear()
    compiled = all(e.rows in COMPILED_KIND for e in pair)
    kinds = tuple(COMPILED_KIND[e.rows] for e in pair if e.rows in COMPILED_KIND)
    names = tuple(e.name for e in pair)
    plan = _plans[key] = _Plan(gen, shown, pair, rest, share, direct, compiled, kinds, names)
    return _remember(methods, all_v, plan)


#: The last plan looked up and the ``methods`` object it was for (a tuple: immutable).
_last_plan: tuple[Sequence[str], bool, _Plan] | None = None


def _remember(methods: Sequence[str], all_v: bool, plan: _Plan) -> _Plan:
    global _last_plan
    if type(methods) is tuple:
        _last_plan = (methods, all_v, plan)
    return plan


def _render_pairs(
    room: RoomBuffers, br: _Brackets, entries: list[InterpolatorInfo], share: bool | None
) -> dict[str, NDArray[np.float64]]:
    """Pair methods on the gathered brackets: each row kernel once (sharing what
    they have in common as ``share`` says), plug-ins through ``f(a, b, s)``.

    The bracketing keyframes are gathered into this thread's rows (:func:`_gather_rows`):
    the same arrays frame after frame, so the kernels keep their views of them.
    """
    n = br.lo.shape[0]
    poses = room.whole().pose_rows
    a, b, ga, gb = _gather_rows(n)
    poses.take(br.lo, 0, ga, "clip")  # lo and hi are valid slots
    poses.take(br.hi, 0, gb, "clip")
    _copyto(a, ga.T)
    _copyto(b, gb.T)
    shared = None if share is None else share_rows(a, b, br.s, share)
    out: dict[str, NDArray[np.float64]] = {}
    for entry in entries:
        if entry.rows is not None:
            # Contiguous rows to write into (faster than strided); the poses are
            # their (n, 7) transpose, a view.
            rows = np.empty((7, n))
            entry.rows(a, b, br.s, rows, None, True, shared, br.ends)
            out[entry.name] = rows.T
        else:  # a plug-in may keep what it is given: its own copies
            out[entry.name] = entry.func(a.T.copy(), b.T.copy(), br.s)
    return out


def _render_room_c(
    ck: ModuleType, room: RoomBuffers, t: float | F64, methods: Sequence[str]
) -> RenderFrame | None:
    """A whole room's frame in one call of the compiled kernels (bracket and every
    method), when every row has keyframes and every method is a compiled pair method
    (what a bot renders); None otherwise.

    The room's tables are held by its compiled renderer (made once, again after the
    room's arrays grow), so a frame passes only its own arrays: its stalls and its
    poses (one block for all methods), the two a frame owns. Each row's bracket
    (the room's ``brackets``) is kept between frames: its next search starts there.
    """
    n = room.n
    if room.filled != n or not n:
        return None
    plan = _plan(methods, True)  # pair methods render themselves, velocities or not
    if plan.rest or not plan.compiled:
        return None
    if isinstance(t, np.ndarray):
        t = _live_times(room, t, room.whole().rows, True)
    renderer: Any = room.renderer
    if renderer is None or type(renderer) is not ck.Renderer:
        renderer = room.renderer = _renderer(ck, room)
    stalled = np.empty(n, dtype=bool)
    poses = np.empty((len(plan.kinds), n, 7))
    renderer.render(n, t, plan.kinds, poses, stalled)
    ran = {name: poses[j] for j, name in enumerate(plan.names)}
    return RenderFrame(ran if plan.direct else {m: ran[m] for m in methods}, stalled)


def _renderer(ck: ModuleType, room: RoomBuffers) -> object:
    """The compiled renderer of ``room``'s arrays (every row, in use or not)."""
    lo, hi, s = room.brackets
    flat_poses = room.pose_rows.reshape(-1, 7)
    return ck.Renderer(room.times.reshape(-1), room.base, room.newest, lo, hi, s, flat_poses)


def _render_pairs_c(
    ck: ModuleType, room: RoomBuffers, br: _Brackets, entries: list[InterpolatorInfo]
) -> dict[str, NDArray[np.float64]]:
    """Pair methods with compiled kernels: each one call on the room's keyframes
    where they lie (no gather), into the frame's own ``(n, 7)`` poses."""
    n = br.lo.shape[0]
    poses = room.whole().pose_rows
    out: dict[str, NDArray[np.float64]] = {}
    for entry in entries:
        assert entry.rows is not None
        res = np.empty((n, 7))
        ck.pair_rows(COMPILED_KIND[entry.rows], poses, br.lo, br.hi, br.s, res)
        out[entry.name] = res
    return out


def _gather_rows(n: int) -> tuple[F64, F64, F64, F64]:
    """This thread's ``(7, n)`` rows for the keyframes either side of ``n`` brackets,
    and the ``(n, 7)`` poses they are gathered into first, kept for the last width
    (a bot's frames all have the same)."""
    rows: tuple[F64, F64, F64, F64] | None = getattr(_local, "gather", None)
    if rows is None or rows[0].shape[1] != n:
        rows = (np.empty((7, n)), np.empty((7, n)), np.empty((n, 7)), np.empty((n, 7)))
        _local.gather = rows
    return rows


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
    keys = room.whole().pose_rows.take(flat, axis=0).reshape(k, n, 7)
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
