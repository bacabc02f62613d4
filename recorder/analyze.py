"""Decimation analysis of a recording or a trace: the paper's Tables 2 and 3.

The paper (Kamarianakis et al., "Less Is More", recording experiment) stores a
VR recording decimated, keeping every 2nd frame (Table 2) or 1 frame in 3
(Table 3), and reconstructs the dropped frames by interpolating the kept ones
at the exact fractions ``a = j / k`` (1/2; 1/3 and 2/3). Its metric is the mean
relative error, in %, of the translation vector and of the Euler-angle vector::

    mean over reconstructed frames of |x_interp - x_true| / |x_true| * 100

for ``x`` = translation (3-vector, metres) and ``x`` = Euler angles (3-vector,
degrees). :func:`analyze` reports that metric exactly, per device class, next
to DESIGN.md's absolute errors of the same reconstructed frames (p50/p95 of
position mm, rotation deg, tip mm; :mod:`interp.metrics`, percentiles as in
:class:`scenarios.qoe.ErrorSamples`).

Choices the paper leaves open, made explicit here:

- Euler angles: the paper's convention is not known to us; the default is
  intrinsic ``XYZ`` in degrees, each angle in [-180, 180) (``euler_seq`` takes
  any of scipy's 24 sequences; :func:`quat_to_euler` is a numpy port of the
  general quaternion method scipy uses). The relative Euler error is taken on
  the raw angle difference, as the metric is written; a difference across the
  +-180 deg seam counts in full. ``euler_rel_wrapped_pct`` reports the same
  metric with each angle difference wrapped into [-180, 180) for comparison.
- Frames whose true vector has zero norm are left out of the relative metric.
- Pair methods run at ``a = j/k``; window methods get the kept neighbours, on
  a time axis of frame indices (so the fractions are the same); velocity
  methods use :meth:`Trace.velocities` with the real time span between the
  kept frames on traces, and on recordings the velocities the updates carried
  (the velocity variant); a recording without them skips them with a note.
- A recording's "full-rate" sequence is each stream's recorded keyframes
  (capture time order, duplicate capture times dropped), one stream at a time.

The paper's own values: not available to us (see :data:`PAPER_VALUES`).
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from posecast.interp import info as interp_info
from posecast.interp import (
    interpolate_brackets,
    position_error_mm,
    rotation_error_deg,
    tip_error_mm,
)
from posecast.recorder.export import sorted_streams
from posecast.scenarios.qoe import CLASS_ORDER, ErrorSamples
from posecast.scenarios.traces import Trace, device_class, find_traces, load_trace

__all__ = [
    "DEFAULT_EULER_SEQ",
    "DEFAULT_KEEP_EVERY",
    "DEFAULT_METHODS",
    "PAPER_VALUES",
    "Sequence7",
    "analyze",
    "decimate",
    "format_analysis",
    "load_sources",
    "quat_to_euler",
    "reconstruct",
    "relative_error_pct",
]

F64 = NDArray[np.float64]

DEFAULT_KEEP_EVERY = (2, 3)
DEFAULT_METHODS = ("soa", "dq-slerp", "motor-lerp")
DEFAULT_EULER_SEQ = "XYZ"

#: The paper's Tables 2 and 3 (mean relative error, %), by keep-every, method,
#: and quantity. ``None``: the published numbers were not available to us when
#: this was written (the paper's tables could not be retrieved), so none are shown.
PAPER_VALUES: dict[int, dict[str, dict[str, float | None]]] = {
    k: {m: {"translation_rel_pct": None, "euler_rel_pct": None} for m in DEFAULT_METHODS}
    for k in DEFAULT_KEEP_EVERY
}
PAPER_NOTE = (
    "paper values: not available (the published Tables 2 and 3 could not be retrieved; "
    "none are quoted)"
)

# Stats reported per class, in table order.
_REL_KEYS = (
    "translation_rel_pct",
    "euler_rel_pct",
    "euler_rel_wrapped_pct",
    "translation_rel_p50_pct",
    "euler_rel_p50_pct",
)
_ABS_KEYS = ("pos_p50_mm", "pos_p95_mm", "rot_p50_deg", "rot_p95_deg", "tip_p50_mm", "tip_p95_mm")


# -- Euler angles -----------------------------------------------------------------------


def quat_to_euler(quat: ArrayLike, seq: str = DEFAULT_EULER_SEQ, degrees: bool = True) -> F64:
    """Euler angles ``(..., 3)`` of unit quaternions ``(..., 4)`` **w first**.

    ``seq``: three axes, uppercase for intrinsic (``"XYZ"``: rotate about x, then
    the new y, then the new z), lowercase for extrinsic, like scipy's
    ``Rotation.as_euler``. Angles are in [-pi, pi) (or degrees), the second in
    [-pi/2, pi/2] for Tait-Bryan sequences. At gimbal lock the third angle is
    set to 0, as scipy does. Method: Bernardes & Viollet (2022), "Quaternion to
    Euler angles conversion: a direct, general and computationally efficient
    method", which needs no rotation matrix.
    """
    q = np.asarray(quat, dtype=np.float64)
    if q.shape[-1:] != (4,):
        raise ValueError(f"Expected `quat` to have shape (..., 4), got {q.shape}")
    if len(seq) != 3 or not (seq.isupper() or seq.islower()) or set(seq.lower()) - set("xyz"):
        raise ValueError(f"Expected `seq` like 'XYZ' (intrinsic) or 'xyz' (extrinsic), got {seq!r}")
    if seq[0] == seq[1] or seq[1] == seq[2]:
        raise ValueError(f"Expected consecutive axes to differ, got {seq!r}")
    extrinsic = seq.islower()
    axes = ["xyz".index(c) for c in seq.lower()]
    if not extrinsic:  # an intrinsic sequence is the reversed extrinsic one
        axes.reverse()
    i, j, k = axes
    symmetric = i == k
    if symmetric:
        k = 3 - i - j
    sign = (i - j) * (j - k) * (k - i) // 2  # Levi-Civita symbol of (i, j, k)
    w = q[..., 0]
    v = q[..., 1:]
    if symmetric:
        a, b, c, d = w, v[..., i], v[..., j], v[..., k] * sign
    else:
        a = w - v[..., j]
        b = v[..., i] + v[..., k] * sign
        c = v[..., j] + w
        d = v[..., k] * sign - v[..., i]
    middle = 2.0 * np.arctan2(np.hypot(c, d), np.hypot(a, b))
    half_sum = np.arctan2(b, a)
    half_diff = np.arctan2(d, c)
    eps = 1e-7
    near_zero = np.abs(middle) <= eps
    near_pi = np.abs(middle - np.pi) <= eps
    regular = ~(near_zero | near_pi)
    # Gimbal lock: only the sum (or difference) of the outer angles is defined;
    # the whole of it goes to one outer angle, the other is 0.
    locked = np.where(near_zero, 2.0 * half_sum, 2.0 * half_diff * (-1.0 if extrinsic else 1.0))
    zero = np.zeros_like(middle)
    first = np.where(regular, half_sum - half_diff, locked if extrinsic else zero)
    third = np.where(regular, half_sum + half_diff, zero if extrinsic else locked)
    if not symmetric:
        third = third * sign
        middle = middle - np.pi / 2
    angles = np.stack([first, middle, third] if extrinsic else [third, middle, first], axis=-1)
    angles = (angles + np.pi) % (2.0 * np.pi) - np.pi
    return np.degrees(angles) if degrees else angles


def relative_error_pct(rendered: ArrayLike, truth: ArrayLike) -> F64:
    """|rendered - truth| / |truth| * 100 over the last axis; NaN where |truth| == 0."""
    r = np.asarray(rendered, dtype=np.float64)
    t = np.asarray(truth, dtype=np.float64)
    num = np.linalg.norm(r - t, axis=-1)
    den = np.linalg.norm(t, axis=-1)
    out: F64 = np.full(num.shape, np.nan)
    np.divide(num, den, out=out, where=den > 0)
    return 100.0 * out


def _wrap_deg(x: F64) -> F64:
    out: F64 = (x + 180.0) % 360.0 - 180.0
    return out


# -- decimation and reconstruction --------------------------------------------------------


@dataclass(frozen=True)
class Sequence7:
    """A full-rate pose sequence of ``S`` streams sharing sample times.

    ``times (N,)`` strictly increasing seconds, ``poses (N, S, 7)`` float64,
    ``streams`` the names (for device classes), ``velocities (N, S, 6)`` if known.
    """

    name: str
    times: F64
    poses: F64
    streams: tuple[str, ...]
    velocities: F64 | None = None
    kind: str = "trace"


def decimate(n: int, keep_every: int) -> tuple[NDArray[np.intp], NDArray[np.intp], F64]:
    """Frames ``0, k, 2k, ...`` kept; for each dropped frame between two kept ones:
    its index, its lower kept frame, and its fraction ``a = j / k``.

    Returns ``(dropped, lo, a)``; frames after the last kept one are not
    reconstructed (nothing brackets them).
    """
    if keep_every < 2:
        raise ValueError(f"keep_every must be at least 2, got {keep_every}")
    last_kept = ((n - 1) // keep_every) * keep_every
    idx = np.arange(last_kept, dtype=np.intp)
    j = idx % keep_every
    dropped = idx[j > 0]
    lo = dropped - dropped % keep_every
    return dropped, lo, (dropped % keep_every) / keep_every


def reconstruct(seq: Sequence7, keep_every: int, method: str) -> tuple[NDArray[np.intp], F64]:
    """The dropped frames' indices and their reconstructed poses ``(M, S, 7)``."""
    n = seq.times.shape[0]
    dropped, lo, a = decimate(n, keep_every)
    hi = lo + keep_every
    entry = interp_info(method)
    last_kept = ((n - 1) // keep_every) * keep_every
    if entry.kind == "window":
        # Kept neighbours (``lookbehind`` before, ``lookahead`` after); a missing
        # one repeats its inward neighbour, which for kept frames 0, k, 2k, ...
        # is clipping to the first and last kept frame. Time axis: frame
        # indices, so the query sits at the same fraction a as for pairs.
        steps_back = np.arange(max(1, entry.lookbehind), 0, -1) * keep_every  # oldest first
        steps_on = np.arange(1, max(1, entry.lookahead) + 1) * keep_every  # nearest first
        before = np.maximum(lo[:, None] - steps_back, 0)
        after = np.minimum(hi[:, None] + steps_on, last_kept)
        times: F64 = np.arange(n, dtype=np.float64)
        rendered = interpolate_brackets(
            seq.poses, lo, hi, a, method, times=times, before=before, after=after
        )
    elif entry.kind == "velocity":
        if seq.velocities is None:
            raise ValueError(f"{method} needs velocities, which {seq.name} does not carry")
        rendered = interpolate_brackets(
            seq.poses, lo, hi, a, method, times=seq.times, velocities=seq.velocities
        )
    else:
        rendered = interpolate_brackets(seq.poses, lo, hi, a, method)
    return dropped, rendered


# -- sources ------------------------------------------------------------------------------


def _trace_sequence(trace: Trace) -> Sequence7:
    return Sequence7(
        trace.name, trace.times, trace.poses, trace.streams, trace.velocities(), "trace"
    )


def _recording_sequences(path: Path) -> list[Sequence7]:
    out = []
    for s in sorted_streams(path):
        t = s.times
        keep = np.ones(t.shape, dtype=bool)
        keep[1:] = t[1:] != t[:-1]  # duplicate capture time: the first one counts
        if int(keep.sum()) < 3:
            continue
        name = s.name or f"stream{s.stream}"
        vel = None  # the velocities the updates carried (velocity variant), if all did
        if s.velocities is not None and not np.isnan(s.velocities[keep]).any():
            vel = s.velocities[keep].astype(np.float64)[:, None, :]
        out.append(
            Sequence7(
                f"{path.stem}/user{s.user}/{name}",
                t[keep],
                s.poses[keep].astype(np.float64)[:, None, :],
                (name,),
                vel,
                "recording",
            )
        )
    return out


def load_sources(
    source: str | os.PathLike[str] | Trace | Iterable[str | os.PathLike[str] | Trace],
) -> list[tuple[str, str, list[Sequence7]]]:
    """Resolve sources to ``(name, kind, sequences)``.

    A source is a :class:`Trace`, a trace CSV, a ``.mcap`` / ``.mcap.part``
    recording, ``traces:dev`` / ``traces:eval`` or a directory of trace CSVs,
    or an iterable of these.
    """
    if isinstance(source, Trace | str | os.PathLike):
        items: list[Any] = [source]
    else:
        items = list(source)
    out: list[tuple[str, str, list[Sequence7]]] = []
    for item in items:
        if isinstance(item, Trace):
            out.append((item.name, "trace", [_trace_sequence(item)]))
            continue
        p = Path(item)
        if p.name.endswith((".mcap", ".mcap.part")):
            out.append((p.name, "recording", _recording_sequences(p)))
        else:
            for f in find_traces(item):
                tr = load_trace(f)
                out.append((tr.name, "trace", [_trace_sequence(tr)]))
    return out


# -- the analysis -------------------------------------------------------------------------


@dataclass
class _Pool:
    """Per-sample errors of one (keep, method, class), pooled over streams and sources."""

    t_rel: list[F64] = field(default_factory=list)
    e_rel: list[F64] = field(default_factory=list)
    e_rel_wrapped: list[F64] = field(default_factory=list)
    absolute: ErrorSamples = field(default_factory=ErrorSamples)

    def add(self, other: _Pool) -> None:
        self.t_rel += other.t_rel
        self.e_rel += other.e_rel
        self.e_rel_wrapped += other.e_rel_wrapped
        self.absolute.merge(other.absolute)

    def stats(self) -> dict[str, float | int]:
        def cat(parts: list[F64]) -> F64:
            return np.concatenate(parts) if parts else np.empty(0)

        t, e, ew = cat(self.t_rel), cat(self.e_rel), cat(self.e_rel_wrapped)

        def mean(x: F64) -> float:
            x = x[np.isfinite(x)]
            return float(x.mean()) if x.size else math.nan

        def median(x: F64) -> float:
            x = x[np.isfinite(x)]
            return float(np.median(x)) if x.size else math.nan

        ab = self.absolute.stats()
        ab.pop("stall_fraction", None)
        return {
            "frames": int(t.size),
            "translation_rel_pct": mean(t),
            "euler_rel_pct": mean(e),
            "euler_rel_wrapped_pct": mean(ew),
            "translation_rel_p50_pct": median(t),
            "euler_rel_p50_pct": median(e),
            "excluded_zero_norm": int(np.count_nonzero(~np.isfinite(t)))
            + int(np.count_nonzero(~np.isfinite(e))),
            **ab,
        }


def _errors(seq: Sequence7, keep: int, method: str, euler_seq: str) -> dict[str, _Pool]:
    dropped, rendered = reconstruct(seq, keep, method)
    truth = seq.poses[dropped]
    t_rel = relative_error_pct(rendered[..., :3], truth[..., :3])
    e_r = quat_to_euler(rendered[..., 3:], euler_seq)
    e_t = quat_to_euler(truth[..., 3:], euler_seq)
    e_rel = relative_error_pct(e_r, e_t)
    e_rel_w = relative_error_pct(e_t + _wrap_deg(e_r - e_t), e_t)
    pos = position_error_mm(rendered, truth)
    rot = rotation_error_deg(rendered, truth)
    tip = tip_error_mm(rendered, truth)
    out: dict[str, _Pool] = {}
    for j, name in enumerate(seq.streams):
        for cls in (device_class(name), "all"):
            pool = out.setdefault(cls, _Pool())
            pool.t_rel.append(t_rel[:, j])
            pool.e_rel.append(e_rel[:, j])
            pool.e_rel_wrapped.append(e_rel_w[:, j])
            pool.absolute.add(pos[:, j], rot[:, j], tip[:, j], 0, dropped.size)
    return out


def _class_order(classes: Iterable[str]) -> list[str]:
    present = set(classes)
    return [c for c in (*CLASS_ORDER, "all") if c in present]


_Sources = list[tuple[str, str, list[Sequence7]]]


def _source_pool(
    seqs: list[Sequence7], keep: int, method: str, needs_velocity: bool, euler_seq: str
) -> tuple[dict[str, _Pool], bool]:
    """One source's errors by class, and whether a sequence lacked velocities.

    A velocity method stops at the first sequence without velocities (what
    came before it still counts).
    """
    src_pool: dict[str, _Pool] = {}
    for seq in seqs:
        if needs_velocity and seq.velocities is None:
            return src_pool, True
        for cls, pool in _errors(seq, keep, method, euler_seq).items():
            src_pool.setdefault(cls, _Pool()).add(pool)
    return src_pool, False


def _method_pools(
    sources: _Sources, keep: int, method: str, euler_seq: str
) -> tuple[dict[str, _Pool], list[str], list[tuple[str, dict[str, Any]]]]:
    """One method's errors pooled over ``sources``, the sources skipped, per-source stats."""
    entry = interp_info(method)
    pooled: dict[str, _Pool] = {}
    skipped: list[str] = []
    per_source: list[tuple[str, dict[str, Any]]] = []
    for name, _kind, seqs in sources:
        src_pool, lacked = _source_pool(seqs, keep, method, entry.needs_velocity, euler_seq)
        if lacked:
            skipped.append(name)
        if not src_pool:
            continue
        per_source.append((name, {cls: src_pool[cls].stats() for cls in _class_order(src_pool)}))
        for cls, pool in src_pool.items():
            pooled.setdefault(cls, _Pool()).add(pool)
    return pooled, skipped, per_source


def _table(
    sources: _Sources, keep: int, methods: Sequence[str], euler_seq: str
) -> tuple[dict[str, Any], list[str], list[tuple[str, str, dict[str, Any]]]]:
    """One keep-every table, its notes, and ``(source, method, stats)`` per source."""
    notes: list[str] = []
    per_source: list[tuple[str, str, dict[str, Any]]] = []
    table_methods: dict[str, Any] = {}
    for m in methods:
        pooled, skipped, by_source = _method_pools(sources, keep, m, euler_seq)
        per_source.extend((name, m, stats) for name, stats in by_source)
        if skipped:
            notes.append(
                f"{m}: skipped for {', '.join(sorted(set(skipped)))} (recorded without "
                "velocities: record bots that send the velocity variant, or use a trace)"
            )
        if pooled:
            table_methods[m] = {
                "classes": {cls: pooled[cls].stats() for cls in _class_order(pooled)}
            }
        else:
            table_methods[m] = {"skipped": "no source with velocities"}
    table = {
        "fractions": [j / keep for j in range(1, keep)],
        "methods": table_methods,
    }
    return table, notes, per_source


def _velocity_note(methods: Sequence[str], sources: _Sources) -> str | None:
    """The caveat on velocity methods run on traces, if any are."""
    if any(interp_info(m).needs_velocity for m in methods) and any(
        kind == "trace" for _n, kind, _s in sources
    ):
        return (
            "velocity methods on traces use Trace.velocities(): central differences of the "
            "full-rate trace, standing in for tracker-reported velocities; at a kept frame they "
            "draw on its dropped neighbours, which favours these methods here"
        )
    return None


def _source_summary(sources: _Sources) -> list[dict[str, Any]]:
    """Name, kind, stream and frame counts and median rate of each source."""
    return [
        {
            "name": name,
            "kind": kind,
            "streams": sum(len(s.streams) for s in seqs),
            "frames": int(sum(s.times.size for s in seqs)),
            "rate_hz": _median_rate(seqs),
        }
        for name, kind, seqs in sources
    ]


def analyze(
    source: str | os.PathLike[str] | Trace | Iterable[str | os.PathLike[str] | Trace],
    keep_every: Sequence[int] = DEFAULT_KEEP_EVERY,
    methods: Sequence[str] = DEFAULT_METHODS,
    *,
    euler_seq: str = DEFAULT_EULER_SEQ,
) -> dict[str, Any]:
    """Drop frames, reconstruct them with each method, and score them (see module doc).

    Returns a JSON-ready dict::

        {"sources": [...], "keep_every": [2, 3], "methods": [...],
         "euler": {...}, "metric": str, "notes": [...], "paper": {...},
         "tables": {"2": {"fractions": [0.5],
                          "methods": {"soa": {"classes": {"hands": {stats},
                                                          "head": {...}, "all": {...}}},
                                      "motor-hermite": {"skipped": "why"}}},
                    "3": ...},
         "per_source": {name: {"2": {method: {class: {stats}}}}}}

    Stats per class: ``frames``, ``translation_rel_pct``, ``euler_rel_pct``
    (the paper's metric), ``euler_rel_wrapped_pct``, medians of both relative
    errors, ``excluded_zero_norm``, and ``pos/rot/tip_p50/p95``.
    """
    for k in keep_every:
        if k < 2:
            raise ValueError(f"keep_every values must be at least 2, got {k}")
    for m in methods:
        interp_info(m)  # KeyError with the known names
    sources = load_sources(source)
    notes: list[str] = []
    tables: dict[str, Any] = {}
    per_source: dict[str, Any] = {}
    for k in keep_every:
        table, table_notes, by_source = _table(sources, k, methods, euler_seq)
        for name, m, stats in by_source:
            per_source.setdefault(name, {}).setdefault(str(k), {})[m] = stats
        for note in table_notes:
            if note not in notes:
                notes.append(note)
        tables[str(k)] = table
    velocity_note = _velocity_note(methods, sources)
    if velocity_note is not None:
        notes.append(velocity_note)
    notes.append(PAPER_NOTE)
    return {
        "sources": _source_summary(sources),
        "keep_every": list(keep_every),
        "methods": list(methods),
        "euler": {
            "sequence": euler_seq,
            "intrinsic": euler_seq.isupper(),
            "units": "deg",
            "range": "[-180, 180)",
        },
        "metric": (
            "mean over reconstructed frames of |x_interp - x_true| / |x_true| * 100, "
            "x = translation (m) and x = Euler angles (deg), Euclidean norm"
        ),
        "notes": notes,
        "paper": {
            "available": False,
            "values": {str(k): v for k, v in PAPER_VALUES.items()},
            "note": PAPER_NOTE,
        },
        "tables": tables,
        "per_source": per_source,
    }


def _median_rate(seqs: Sequence[Sequence7]) -> float:
    rates = [1.0 / float(np.median(np.diff(s.times))) for s in seqs if s.times.size > 1]
    return float(np.median(rates)) if rates else math.nan


# -- text ---------------------------------------------------------------------------------


def _f(x: Any, digits: int = 2) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return f"{x:.{digits}f}"


def _paper(result: dict[str, Any], k: str, m: str, key: str) -> str:
    v = result.get("paper", {}).get("values", {}).get(k, {}).get(m, {}).get(key)
    return "n/a" if v is None else _f(v)


def format_analysis(result: dict[str, Any]) -> str:
    """Markdown tables of :func:`analyze`'s result: one per keep-every value."""
    lines: list[str] = []
    srcs = result["sources"]
    names = ", ".join(s["name"] for s in srcs)
    lines.append(f"Sources ({len(srcs)}): {names}")
    eu = result["euler"]
    kind = "intrinsic" if eu["intrinsic"] else "extrinsic"
    lines.append(f"Euler angles: {eu['sequence']} ({kind}), degrees in {eu['range']}")
    lines.append(f"Metric: {result['metric']}")
    for k, table in result["tables"].items():
        fr = ", ".join(f"{a:.3g}" for a in table["fractions"])
        lines.append("")
        lines.append(f"Keep 1 in {k} (interpolate at a = {fr})")
        lines.append("")
        lines.append(
            "| method | class | frames | transl. rel % | paper | Euler rel % | paper "
            "| Euler rel % (wrapped) | pos p50/p95 mm | rot p50/p95 deg | tip p50/p95 mm |"
        )
        lines.append("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
        for m, entry in table["methods"].items():
            if "skipped" in entry:
                lines.append(f"| {m} | skipped: {entry['skipped']} |||||||||| ")
                continue
            for cls, st in entry["classes"].items():
                lines.append(
                    f"| {m} | {cls} | {st['frames']} | {_f(st['translation_rel_pct'], 3)} "
                    f"| {_paper(result, k, m, 'translation_rel_pct')} "
                    f"| {_f(st['euler_rel_pct'], 3)} | {_paper(result, k, m, 'euler_rel_pct')} "
                    f"| {_f(st['euler_rel_wrapped_pct'], 3)} "
                    f"| {_f(st['pos_p50_mm'])} / {_f(st['pos_p95_mm'])} "
                    f"| {_f(st['rot_p50_deg'])} / {_f(st['rot_p95_deg'])} "
                    f"| {_f(st['tip_p50_mm'])} / {_f(st['tip_p95_mm'])} |"
                )
    if result["notes"]:
        lines.append("")
        lines.extend(f"Note: {n}" for n in result["notes"])
    return "\n".join(lines)
