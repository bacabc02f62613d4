"""Error versus latency: the equal-QoE search over rate, playout delay and stall policy.

Hands only, every method at a few rates and playout delays, each with the
stall policies of :data:`~scenarios.table1.common.VARIANTS`, on the ideal
network and through each tier's link (:func:`_frontier_sweep`). From those
points: the frontier (best headline within each latency budget,
:func:`pareto_frontier`), the rates bisected where a verdict needs them
(:func:`_refine`) and the verdicts (:func:`_frontier_verdicts`);
:func:`frontier_report` runs them all and returns the report's ``frontier`` key.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from posecast import interp
from posecast.scenarios.network import VELOCITY_BYTES_PER_POSE, Tier, Transport
from posecast.scenarios.qoe import (
    KeyframeLog,
    Playout,
    Rendered,
    StallPlan,
    apply_stalls,
    interpolate_playout,
    plan_stalls,
    playout_brackets,
    window_depth,
)
from posecast.scenarios.table1.common import F64, FRONTIER_RATES, PAPER, VARIANTS, saving_pct
from posecast.scenarios.table1.sweep import _ideal_log, _link_log_maker, _LogMaker, _Wire
from posecast.scenarios.traces import Trace, device_class

#: ``(network name, keyframe log maker, rates)`` of one network of the view.
_Network = tuple[str, _LogMaker, Sequence[int]]


def pareto_frontier(
    points: Iterable[Mapping[str, Any]], x: str = "latency_ms", y: str = "headline_mm"
) -> list[dict[str, Any]]:
    """The points no other point beats on both ``x`` and ``y`` (lower is better), by ``x``.

    Reading it as a step function gives the best ``y`` within each ``x``
    budget: each point's ``y`` is strictly lower than that of every point with
    a smaller or equal ``x``. Points with a missing or non-finite value are
    left out.
    """

    def ok(p: Mapping[str, Any]) -> bool:
        vx, vy = p.get(x), p.get(y)
        return (
            isinstance(vx, int | float)
            and isinstance(vy, int | float)
            and math.isfinite(vx)
            and math.isfinite(vy)
        )

    out: list[dict[str, Any]] = []
    best = math.inf
    for p in sorted((p for p in points if ok(p)), key=lambda p: (p[x], p[y])):
        if p[y] < best:
            out.append(dict(p))
            best = p[y]
    return out


def cheapest_point(
    points: Iterable[Mapping[str, Any]],
    max_latency_ms: float,
    max_headline_mm: float,
    methods: Iterable[str] | None = None,
) -> dict[str, Any] | None:
    """The point with the fewest bytes/s at no more latency and no more headline error.

    ``methods`` limits the candidates. Ties go to the lower latency, then the
    lower headline. ``None`` if no point qualifies.
    """
    allowed = None if methods is None else set(methods)
    best: dict[str, Any] | None = None
    for p in points:
        if allowed is not None and p["method"] not in allowed:
            continue
        lat, head, bw = p.get("latency_ms"), p.get("headline_mm"), p.get("bytes_per_s")
        if lat is None or head is None or bw is None:
            continue
        if not (lat <= max_latency_ms + 1e-9 and head <= max_headline_mm):
            continue
        key = (bw, lat, head)
        if best is None or key < (best["bytes_per_s"], best["latency_ms"], best["headline_mm"]):
            best = dict(p)
    return best


def _tips(poses: F64) -> F64:
    """Tip points ``p + R (0, 0, -TIP_OFFSET_M)``: the tip error's points, in closed form."""
    w, x, y, z = poses[..., 3], poses[..., 4], poses[..., 5], poses[..., 6]
    n2 = w * w + x * x + y * y + z * z
    k = -2.0 * interp.TIP_OFFSET_M / n2
    out = np.empty((*poses.shape[:-1], 3))
    out[..., 0] = poses[..., 0] + k * (x * z + w * y)
    out[..., 1] = poses[..., 1] + k * (y * z - w * x)
    out[..., 2] = poses[..., 2] - interp.TIP_OFFSET_M - k * (x * x + y * y)
    return out


def _tip_mm(poses: F64, true_tips: F64) -> F64:
    d = _tips(poses) - true_tips
    out: F64 = 1000.0 * np.sqrt(np.einsum("...i,...i->...", d, d))
    return out


@dataclass
class _Acc:
    """One point's samples pooled over traces (hands streams)."""

    tip: list[F64] = field(default_factory=list)
    jumps: list[F64] = field(default_factory=list)
    stalls: int = 0
    extrapolated: int = 0
    samples: int = 0
    d_weighted: float = 0.0


def _same_bracket(
    play: Playout, ref: Playout, lookbehind: int, lookahead: int
) -> NDArray[np.bool_]:
    """Queries whose bracket (and the neighbours a window method uses) equal the reference's."""
    same: NDArray[np.bool_] = (play.lo == ref.lo) & (play.hi == ref.hi)
    if lookbehind:
        assert play.before is not None and ref.before is not None
        same &= np.all(play.before[:, -lookbehind:] == ref.before[:, -lookbehind:], axis=1)
    if lookahead:
        assert play.after is not None and ref.after is not None
        same &= np.all(play.after[:, :lookahead] == ref.after[:, :lookahead], axis=1)
    return same


@dataclass
class _PlayCache:
    """Playouts and stall plans of one arrival pattern, shared by methods and wire variants."""

    plays: dict[float, Playout] = field(default_factory=dict)
    plans: dict[tuple[float, float, float, bool], StallPlan] = field(default_factory=dict)
    #: Neighbours gathered (before, after): the widest window of the methods.
    depth: tuple[int, int] = (1, 1)

    def play(self, log: KeyframeLog, taus: F64, d: float) -> Playout:
        out = self.plays.get(d)
        if out is None:
            lb, la = self.depth
            out = self.plays[d] = playout_brackets(
                log.capture, log.arrival, taus, d, lookbehind=lb, lookahead=la
            )
        return out

    def plan(
        self, log: KeyframeLog, taus: F64, d: float, horizon: float, t_c: float, velocity: bool
    ) -> StallPlan:
        key = (d, horizon, t_c, velocity)
        out = self.plans.get(key)
        if out is None:
            out = self.plans[key] = plan_stalls(
                log,
                taus,
                self.play(log, taus, d),
                horizon=horizon,
                correction_time=t_c,
                velocity=velocity,
            )
        return out


def _frontier_trace(
    log: KeyframeLog,
    lag: float,
    rate: int,
    taus: F64,
    true_tips: F64,
    methods: Sequence[str],
    fractions: Sequence[float],
    horizon: float,
    correction_time: float,
    acc: dict[tuple[str, float, str], _Acc],
    cache: _PlayCache,
) -> None:
    """Every (method, f, variant) on one trace's hands keyframes, pooled into ``acc``.

    Each query is rendered as :func:`scenarios.qoe.evaluate_group` renders it.
    To save work, a bracketed query whose bracket (and neighbours) match those
    with every keyframe arrived reuses that render, a held query shows its
    keyframe (what every interpolator returns at s = 0), and what stalls show
    is planned once per playout delay (:func:`scenarios.qoe.plan_stalls`).
    """
    if not (taus.size and log.capture.size):
        return
    lb_max, la_max = cache.depth
    ref = playout_brackets(
        log.capture, log.arrival, taus, math.inf, lookbehind=lb_max, lookahead=la_max
    )
    kf_tips = _tips(log.poses)
    for m in methods:
        entry = interp.info(m)
        ref_poses = interpolate_playout(log, ref, m)
        ref_err = _tip_mm(ref_poses, true_tips)
        for f in fractions:
            d = lag + (f + entry.lookahead) / rate
            play = cache.play(log, taus, d)
            poses, err = _render_play(log, play, ref, ref_poses, ref_err, kf_tips, true_tips, m)
            base = poses[~play.missing]
            hold = apply_stalls(cache.plan(log, taus, d, 0.0, 0.0, False), base)
            ext = apply_stalls(
                cache.plan(log, taus, d, horizon, correction_time, entry.needs_velocity), base
            )
            counts = (taus.size, log.poses.shape[1])
            _pool_variants(acc, (m, f, d), play, err, true_tips, hold, ext, counts)


def _render_play(
    log: KeyframeLog,
    play: Playout,
    ref: Playout,
    ref_poses: F64,
    ref_err: F64,
    kf_tips: F64,
    true_tips: F64,
    m: str,
) -> tuple[F64, F64]:
    """Poses and tip errors of ``m`` at one playout delay, reusing the all-arrived render."""
    entry = interp.info(m)
    assert play.before is not None and play.after is not None
    shown = ~play.missing
    stall = play.stall & shown
    redo = shown & ~stall & ~_same_bracket(play, ref, entry.lookbehind, entry.lookahead)
    poses, err = ref_poses, ref_err
    if stall.any() or redo.any():
        poses, err = ref_poses.copy(), ref_err.copy()
    if stall.any():
        hold = play.hi[stall]
        poses[stall] = log.poses[hold]
        d_tip = kf_tips[hold] - true_tips[stall]
        err[stall] = 1000.0 * np.sqrt(np.einsum("...i,...i->...", d_tip, d_tip))
    if redo.any():
        poses[redo] = interpolate_playout(log, play, m, redo)
        err[redo] = _tip_mm(poses[redo], true_tips[redo])
    return poses, err


def _pool_variants(
    acc: dict[tuple[str, float, str], _Acc],
    point: tuple[str, float, float],
    play: Playout,
    err: F64,
    true_tips: F64,
    hold_ren: Rendered,
    ext_ren: Rendered,
    counts: tuple[int, int],
) -> None:
    """Pool one render into ``acc`` under each stall policy of :data:`VARIANTS`.

    ``point``: (method, f, playout delay D); ``counts``: (queries, hands streams).
    """
    m, f, d = point
    n_taus, s_count = counts
    shown = ~play.missing
    n_stall = int(play.stall.sum()) * s_count
    n_q = n_taus * s_count
    e_shown = err[shown]
    tips_shown = true_tips[shown]
    for variant in VARIANTS:
        a = acc.setdefault((m, f, variant), _Acc())
        a.stalls += n_stall
        a.samples += n_q
        a.d_weighted += d * n_q
        if variant == "hold":
            a.jumps.append(hold_ren.jump_tip_mm.reshape(-1))
            a.tip.append(e_shown.reshape(-1))
            continue
        a.jumps.append(ext_ren.jump_tip_mm.reshape(-1))
        a.extrapolated += int(ext_ren.extrapolated.sum()) * s_count
        changed = ext_ren.extrapolated[shown]
        shown_poses = ext_ren.unblended
        if variant == "smooth":
            changed = changed | ext_ren.corrected[shown]
            shown_poses = ext_ren.poses
        e = e_shown
        if changed.any():
            assert shown_poses is not None
            e = e_shown.copy()
            e[changed] = _tip_mm(shown_poses[changed], tips_shown[changed])
        a.tip.append(e.reshape(-1))


def _frontier_sweep(
    trs: Sequence[Trace],
    networks: Sequence[_Network],
    methods: Sequence[str],
    wire: _Wire,
    fractions: Sequence[float],
    horizon: float,
    correction_time: float,
    tick: Callable[[], None],
) -> list[dict[str, Any]]:
    """Headline, latency, stalls and bytes/s of every (network, method, rate, f, variant)."""
    hands = [
        (i, [j for j, s in enumerate(tr.streams) if device_class(s) == "hands"])
        for i, tr in enumerate(trs)
    ]
    hands = [(i, cols) for i, cols in hands if cols]
    view = _View(methods, wire, fractions, horizon, correction_time)
    points: list[dict[str, Any]] = []
    for net_name, make_log, rates in networks:
        for rate in rates:
            acc: dict[tuple[str, float, str], _Acc] = {}
            for i, cols in hands:
                _frontier_hands(trs[i], i, cols, make_log, rate, view, acc)
                tick()
            points += [_point(net_name, rate, key, a, wire) for key, a in acc.items()]
    return points


@dataclass(frozen=True)
class _View:
    """What the error-versus-latency view evaluates at each (network, rate)."""

    methods: Sequence[str]
    wire: _Wire
    fractions: Sequence[float]
    horizon: float
    correction_time: float


def _frontier_hands(
    tr: Trace,
    i: int,
    cols: list[int],
    make_log: _LogMaker,
    rate: int,
    view: _View,
    acc: dict[tuple[str, float, str], _Acc],
) -> None:
    """One trace's hands streams (``cols``) at ``rate``, every wire variant, into ``acc``."""
    wire = view.wire
    tr_h = Trace(tr.name, tr.times, tr.poses[:, cols], tuple(tr.streams[j] for j in cols))
    vel = wire.velocities[i]
    caches: list[tuple[KeyframeLog, _PlayCache]] = []
    for fb, needs_v, ms in wire.groups(view.methods):
        v = None if (vel is None or not needs_v) else vel[:, cols]
        log, d1, window, _ = make_log(i, tr_h, rate, fb, v)
        # Wire variants whose keyframes arrived alike share playouts and plans.
        cache = next(
            (
                c
                for other, c in caches
                if np.array_equal(other.capture, log.capture)
                and np.array_equal(other.arrival, log.arrival)
            ),
            None,
        )
        if cache is None:
            cache = _PlayCache(depth=window_depth(view.methods))
            caches.append((log, cache))
        q = (tr_h.times >= window[0]) & (tr_h.times <= window[1])
        _frontier_trace(
            log,
            d1 - 1.0 / rate,
            rate,
            tr_h.times[q],
            _tips(tr_h.poses[q]),
            ms,
            view.fractions,
            view.horizon,
            view.correction_time,
            acc,
            cache,
        )


def _point(
    net_name: str, rate: int, key: tuple[str, float, str], a: _Acc, wire: _Wire
) -> dict[str, Any]:
    """One point of the view from its pooled samples."""
    m, f, variant = key
    tip = np.concatenate(a.tip) if a.tip else np.empty(0)
    jumps = np.concatenate(a.jumps) if a.jumps else np.empty(0)
    d_mean = a.d_weighted / a.samples if a.samples else math.nan
    t50, t95 = np.percentile(tip, [50, 95]) if tip.size else (math.nan, math.nan)
    j50, j95 = np.percentile(jumps, [50, 95]) if jumps.size else (math.nan, math.nan)
    return {
        "network": net_name,
        "method": m,
        "rate": rate,
        "fraction": f,
        "variant": variant,
        "lookahead": wire.lookahead[m],
        "latency_ms": 1000.0 * d_mean,
        "headline_mm": float(t95),
        "tip_p50_mm": float(t50),
        "stall_fraction": a.stalls / a.samples if a.samples else math.nan,
        "extrapolated_fraction": (a.extrapolated / a.samples if a.samples else math.nan),
        "correction_events": int(jumps.size),
        "correction_tip_p50_mm": float(j50),
        "correction_tip_p95_mm": float(j95),
        "wire_bytes": wire.frame_bytes[m],
        "bytes_per_s": float(rate * wire.frame_bytes[m]),
    }


def _qualifies(
    points: Sequence[Mapping[str, Any]], net: str, m: str, r: int, lat: float, head: float
) -> bool:
    """Whether ``m`` at ``r`` on ``net`` has a point within both bounds."""
    return any(
        p["network"] == net
        and p["method"] == m
        and p["rate"] == r
        and p["latency_ms"] <= lat + 1e-9
        and p["headline_mm"] <= head
        for p in points
    )


def _refine(
    points: list[dict[str, Any]],
    methods: Sequence[str],
    soa_rates: Mapping[str, int],
    networks: Sequence[_Network],
    min_rate: int,
    evaluate: Callable[[str, _LogMaker, str, list[int]], list[dict[str, Any]]],
) -> dict[str, dict[str, list[int]]]:
    """Bisect the integer rates below each verdict's cheapest grid rate; extend ``points``.

    For every reference of :func:`_frontier_verdicts` (SoA at each tier rate;
    on the ideal network also SoA at 30 Hz without a latency bound, for the
    posecast methods) and every paper or posecast method that reaches it on
    the grid: bisect between its cheapest qualifying grid rate and the grid
    rate below it, assuming that a method which qualifies at a rate also
    qualifies at every higher one. ``evaluate(network, maker, method, rates)``
    returns the new points. Returns the rates added, by network and method.
    """
    ours = _ours(methods)
    cands = [m for m in methods if m != "soa"]
    added: dict[str, dict[str, list[int]]] = {}
    for net, maker, rates in networks:
        refs: list[tuple[float, float, list[str]]] = []
        pts = [p for p in points if p["network"] == net]
        for tier, r_soa in soa_rates.items():
            if net in (tier, "ideal") and (ref := _find(pts, net, "soa", r_soa, 1.0)):
                refs.append((ref["latency_ms"], ref["headline_mm"], cands))
        if net == "ideal" and (ref := _find(pts, net, "soa", 30, 1.0)):
            refs.append((math.inf, ref["headline_mm"], ours))
        top = max(rates, default=0)
        done: dict[str, set[int]] = {m: set(rates) for m in cands}

        # (method, latency bound, headline bound) -> (highest failing, lowest qualifying)
        searches: dict[tuple[str, float, float], tuple[int, int]] = {}
        for lat, head, ms in refs:
            for m in ms:
                ok = [r for r in done[m] if _qualifies(points, net, m, r, lat, head)]
                if ok:
                    r_c = min(ok)
                    below = [r for r in done[m] if r < r_c]
                    searches[(m, lat, head)] = (max(below) if below else min_rate - 1, r_c)
        while True:
            todo: dict[str, set[int]] = {}
            for (m, _, _), (lo, hi) in searches.items():
                if hi - lo > 1:
                    mid = (lo + hi) // 2
                    if mid <= top and mid not in done[m]:
                        todo.setdefault(m, set()).add(mid)
            if not todo:
                break
            for m, rs in todo.items():
                points += evaluate(net, maker, m, sorted(rs))
                done[m] |= rs
                added.setdefault(net, {}).setdefault(m, []).extend(sorted(rs))
            for key, (lo, hi) in list(searches.items()):
                m, lat, head = key
                if hi - lo > 1:
                    mid = (lo + hi) // 2
                    searches[key] = (
                        (lo, mid) if _qualifies(points, net, m, mid, lat, head) else (mid, hi)
                    )
    return {n: {m: sorted(set(r)) for m, r in d.items()} for n, d in added.items()}


def _ours(methods: Sequence[str]) -> list[str]:
    """posecast's own methods: neither SoA nor one of the paper's."""
    return [m for m in methods if m != "soa" and m not in PAPER["ga_methods"]]


def _find(
    points: Sequence[Mapping[str, Any]], network: str, method: str, rate: int, fraction: float
) -> dict[str, Any] | None:
    for p in points:
        if (
            p["network"] == network
            and p["method"] == method
            and p["rate"] == rate
            and p["fraction"] == fraction
            and p["variant"] == "hold"
        ):
            return dict(p)
    return None


def _short(p: Mapping[str, Any] | None) -> dict[str, Any] | None:
    if p is None:
        return None
    keys = (
        "network",
        "method",
        "rate",
        "fraction",
        "variant",
        "latency_ms",
        "headline_mm",
        "stall_fraction",
        "correction_tip_p95_mm",
        "bytes_per_s",
    )
    return {k: p[k] for k in keys}


def _frontier_verdicts(
    points: Sequence[Mapping[str, Any]],
    methods: Sequence[str],
    soa_rates: Mapping[str, int],
    networks: Sequence[str],
) -> dict[str, Any]:
    """The issue's two questions, answered from the points.

    (1) Headline target, ideal network: the posecast method and configuration
    (rate <= 10 Hz, any D and variant) with the lowest latency whose headline is
    no worse than SoA at 30 Hz (f = 1, hold). (2) Per tier, on the tier's link
    and on the ideal network at the tier's rate: with SoA at the tier rate
    (f = 1, hold) as the reference, the cheapest configuration (bytes/s) of
    each method at no more latency and no more headline error.
    """
    ours = _ours(methods)
    paper = [m for m in methods if m in PAPER["ga_methods"]]
    out: dict[str, Any] = {"posecast_methods": ours, "paper_methods": paper}
    ideal = [p for p in points if p["network"] == "ideal"]
    ref30 = _find(ideal, "ideal", "soa", 30, 1.0)
    if ref30 is not None:
        out["headline_target"] = _headline_target(ideal, ref30, methods, ours)
    tiers: list[dict[str, Any]] = []
    for tier, r_soa in soa_rates.items():
        for net in (tier, "ideal"):
            if net not in networks:
                continue
            pts = [p for p in points if p["network"] == net]
            ref = _find(pts, net, "soa", r_soa, 1.0)
            if ref is None:
                continue
            tiers.append(_tier_verdict(tier, net, r_soa, pts, ref, methods, ours, paper))
    out["tiers"] = tiers
    return out


def _headline_target(
    ideal: Sequence[Mapping[str, Any]],
    ref30: Mapping[str, Any],
    methods: Sequence[str],
    ours: Sequence[str],
) -> dict[str, Any]:
    """Question (1): a posecast method at <= 10 Hz as good as SoA at 30 Hz (``ref30``)."""
    cands = [
        p
        for p in ideal
        if p["method"] in ours and p["rate"] <= 10 and p["headline_mm"] <= ref30["headline_mm"]
    ]
    best = min(cands, key=lambda p: (p["latency_ms"], p["bytes_per_s"]), default=None)
    # How close each method gets at <= 10 Hz, and the lowest rate matching at all.
    closest = {
        m: _short(
            min(
                (p for p in ideal if p["method"] == m and p["rate"] <= 10),
                key=lambda p: p["headline_mm"],
                default=None,
            )
        )
        for m in methods
    }
    lowest = {}
    for m in methods:
        ok = [p for p in ideal if p["method"] == m and p["headline_mm"] <= ref30["headline_mm"]]
        lowest[m] = _short(min(ok, key=lambda p: (p["rate"], p["latency_ms"]), default=None))
    return {
        "reference": _short(ref30),
        "met": best is not None,
        "best": _short(best),
        "added_latency_ms": None if best is None else best["latency_ms"] - ref30["latency_ms"],
        "bytes_saving_pct": (
            None if best is None else saving_pct(best["bytes_per_s"], ref30["bytes_per_s"])
        ),
        "updates_saving_pct": None if best is None else saving_pct(best["rate"], 30),
        "closest_at_10hz_or_less": closest,
        "lowest_matching_rate": lowest,
    }


def _tier_verdict(
    tier: str,
    net: str,
    r_soa: int,
    pts: Sequence[Mapping[str, Any]],
    ref: Mapping[str, Any],
    methods: Sequence[str],
    ours: Sequence[str],
    paper: Sequence[str],
) -> dict[str, Any]:
    """Question (2) for one tier on one network: each method's cheapest match of ``ref``."""
    cheapest = {
        m: _short(cheapest_point(pts, ref["latency_ms"], ref["headline_mm"], [m])) for m in methods
    }

    def bytes_of(ms: Sequence[str]) -> float:
        vals = [c["bytes_per_s"] for m in ms if (c := cheapest[m]) is not None]
        return min(vals) if vals else math.inf

    b_ours, b_paper, b_soa = bytes_of(ours), bytes_of(paper), bytes_of(["soa"])
    found = [c for m in ours if (c := cheapest[m]) is not None]
    winner = min(found, key=lambda p: p["bytes_per_s"], default=None)
    saving: dict[str, float | None] = {}
    for m in methods:
        c = cheapest[m]
        saving[m] = None if c is None else saving_pct(c["bytes_per_s"], ref["bytes_per_s"])
    return {
        "tier": tier,
        "network": net,
        "soa_rate": r_soa,
        "reference": _short(ref),
        "cheapest": cheapest,
        "bytes_saving_pct": saving,
        "posecast_beats_both_paper_methods": bool(math.isfinite(b_ours) and b_ours < b_paper),
        "posecast_beats_soa": bool(math.isfinite(b_ours) and b_ours < b_soa),
        "paper_methods_reach_reference": bool(math.isfinite(b_paper)),
        "posecast_winner": winner,
    }


# ---------------------------------------------------------------- the Table 1 stage


def frontier_networks(
    tiers: Sequence[Tier],
    soa_rates: Mapping[str, int],
    rate_list: Sequence[int],
    frontier_rates: Iterable[int] | None,
    *,
    link: bool,
    seed: int,
    transport: Transport,
) -> list[_Network]:
    """The view's networks: ideal, then (with ``link``) each tier's link up to its rate.

    Rates: ``frontier_rates`` (default :data:`FRONTIER_RATES` inside the rate
    range), plus the tiers' SoA rates.
    """
    if frontier_rates is None:
        f_rates = {r for r in FRONTIER_RATES if rate_list[0] <= r <= rate_list[-1]}
    else:
        f_rates = {int(r) for r in frontier_rates}
    f_rate_list = sorted(f_rates | set(soa_rates.values()))
    nets: list[_Network] = [("ideal", _ideal_log, f_rate_list)]
    for ti, tier in enumerate(tiers if link else []):
        allowed = [r for r in f_rate_list if r <= soa_rates[tier.name]]
        nets.append((tier.name, _link_log_maker(tier, ti, seed, transport), allowed))
    return nets


def frontier_report(
    trs: Sequence[Trace],
    f_nets: Sequence[_Network],
    meths: Sequence[str],
    wire: _Wire,
    soa_rates: Mapping[str, int],
    min_rate: int,
    *,
    fractions: Sequence[float],
    horizon: float,
    correction_time: float,
    tick: Callable[[], None],
) -> dict[str, Any]:
    """The report's ``frontier`` key: the view's points, refined, its frontiers and verdicts."""
    points = _frontier_sweep(trs, f_nets, meths, wire, fractions, horizon, correction_time, tick)
    net_names = [n for n, _, _ in f_nets]

    # Refine: bisect the rates below each verdict's cheapest grid rate.
    def evaluate(name: str, maker: _LogMaker, m: str, extra: list[int]) -> list[dict[str, Any]]:
        return _frontier_sweep(
            trs,
            [(name, maker, extra)],
            [m],
            wire,
            fractions,
            horizon,
            correction_time,
            lambda: None,
        )

    refined = _refine(points, meths, soa_rates, f_nets, min_rate, evaluate)
    return {
        "config": _frontier_config(f_nets, refined, meths, fractions, horizon, correction_time),
        "points": points,
        "frontiers": {
            n: pareto_frontier(p for p in points if p["network"] == n) for n in net_names
        },
        "verdicts": _frontier_verdicts(points, meths, soa_rates, net_names),
    }


def _frontier_config(
    f_nets: Sequence[_Network],
    refined: Mapping[str, Any],
    meths: Sequence[str],
    fractions: Sequence[float],
    horizon: float,
    correction_time: float,
) -> dict[str, Any]:
    """The ``frontier.config`` key: what the view measured, and how."""
    return {
        "streams": "hands only (the headline's class)",
        "rates": {n: list(r) for n, _, r in f_nets},
        "refined_rates": refined,
        "fractions": list(fractions),
        "playout": "D = (f + look-ahead) / rate + lag; lag = 1/native_rate on the "
        "ideal network, p95(arrival - capture) of the run on a link",
        "latency": "capture to display = D (keyframe ages count from capture, so the "
        "network delay is inside D)",
        "variants": {
            "hold": "a stall holds the newest arrived keyframe (DESIGN.md)",
            "extrapolate": "a stall dead-reckons the newest keyframe for up to the "
            "horizon, then holds; the correction is applied at once (a jump)",
            "smooth": "as extrapolate, the correction blended in over the correction "
            "time (ScLERP, smoothstep weight)",
        },
        "extrapolation": {
            m: "velocity (constant twist from the newest keyframe's velocity)"
            if interp.info(m).needs_velocity
            else "screw (ScLERP of the two newest arrived keyframes continued)"
            for m in meths
        },
        "extrapolate_horizon_s": horizon,
        "correction_time_s": correction_time,
        "bytes_per_s": "rate x wire bytes of a room snapshot for the method (velocity "
        f"variant: +{VELOCITY_BYTES_PER_POSE} B per pose, 6 x float16)",
    }
