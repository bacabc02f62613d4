"""QoE against update rate for every method, on the ideal network and through tier links.

One sweep evaluates every method at every rate over the traces (:func:`_sweep`);
the stages on top turn sweeps into the report's rows: the ideal-network
equal-QoE rates per tier (:func:`ideal_tier_rows`), the same through each
tier's link (:func:`link_rows`) and every trace on its own
(:func:`per_trace_report`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from posecast import interp
from posecast.scenarios.network import LinkModel, Tier, Transport
from posecast.scenarios.qoe import (
    ErrorSamples,
    KeyframeLog,
    evaluate_group,
    ideal_delay,
    ideal_log,
    sample_keyframes,
    summarize,
)
from posecast.scenarios.table1.common import (
    CURVE_KEYS,
    F64,
    HEADLINE,
    PAPER,
    SMOOTHNESS,
    Stats,
    equal_qoe_rate,
    keyframe_velocities,
    method_wire_bytes,
    saving_pct,
    snapped_range,
)
from posecast.scenarios.table1.smoothness import gain_split
from posecast.scenarios.traces import Trace

#: ``stage(name)`` gives the tick to call once per trace done in that stage.
StageTicks = Callable[[str], Callable[[], None]]


@dataclass
class _Net:
    """Per-run network figures, summed over traces (for means)."""

    sent: int = 0
    delivered: int = 0
    lost: int = 0
    skipped: int = 0
    delay_sum: float = 0.0
    d_weighted: float = 0.0
    samples: int = 0

    def add(self, other: _Net) -> None:
        for f in ("sent", "delivered", "lost", "skipped", "delay_sum", "d_weighted", "samples"):
            setattr(self, f, getattr(self, f) + getattr(other, f))

    def summary(self) -> dict[str, float]:
        mean_delay = self.delay_sum / self.delivered if self.delivered else float("nan")
        d = self.d_weighted / self.samples if self.samples else float("nan")
        return {
            "network_delay_ms": 1000.0 * mean_delay,
            "playout_delay_ms": 1000.0 * d,
            "latency_ms": 1000.0 * (d + mean_delay),
            "loss_fraction": self.lost / self.sent if self.sent else float("nan"),
            "skipped_fraction": self.skipped / self.sent if self.sent else float("nan"),
        }


#: ``make_log(trace_index, trace, rate, frame_bytes, velocities) -> (log, D, window, net)``:
#: D is the one-interval playout delay ``1/rate + lag`` of a method without look-ahead.
_LogMaker = Callable[
    [int, Trace, int, int, F64 | None], tuple[KeyframeLog, float, tuple[float, float], _Net]
]


def _ideal_log(
    i: int, trace: Trace, rate: int, frame_bytes: int = 0, velocities: F64 | None = None
) -> tuple[KeyframeLog, float, tuple[float, float], _Net]:
    log = ideal_log(trace.times, trace.poses, rate, velocities)
    n_sent = log.capture.shape[0]
    window = (float(log.capture[0]), float(log.capture[-1]))
    d = ideal_delay(rate, trace.native_rate)
    n_q = int(np.count_nonzero((trace.times >= window[0]) & (trace.times <= window[1])))
    return log, d, window, _Net(n_sent, n_sent, 0, 0, 0.0, d * n_q, n_q)


def _link_log_maker(tier: Tier, tier_index: int, seed: int, transport: Transport) -> _LogMaker:
    def make(
        i: int, trace: Trace, rate: int, frame_bytes: int, velocities: F64 | None
    ) -> tuple[KeyframeLog, float, tuple[float, float], _Net]:
        send, idx = sample_keyframes(trace.times, rate)
        capture = trace.times[idx]
        link = LinkModel(
            tier, np.random.SeedSequence([seed, tier_index, i, rate]), transport=transport
        )
        dl = link.transmit(send, frame_bytes)
        ok = dl.delivered
        log = KeyframeLog(
            capture=capture[ok],
            arrival=dl.arrival[ok],
            poses=trace.poses[idx][ok],
            velocities=None if velocities is None else velocities[idx][ok],
        )
        age = dl.arrival[ok] - capture[ok]
        d = 1.0 / rate + (float(np.percentile(age, 95)) if age.size else 0.0)
        window = (float(capture[0]), float(capture[-1]))
        n_q = int(np.count_nonzero((trace.times >= window[0]) & (trace.times <= window[1])))
        net = _Net(
            sent=len(send),
            delivered=int(ok.sum()),
            lost=int(dl.lost.sum()),
            skipped=int(dl.skipped.sum()),
            delay_sum=float(np.sum(dl.delay[ok])),
            d_weighted=d * n_q,
            samples=n_q,
        )
        return log, d, window, net

    return make


@dataclass(frozen=True)
class _Wire:
    """How each method's keyframes travel: snapshot wire bytes and velocities."""

    frame_bytes: dict[str, int]
    lookahead: dict[str, int]
    #: per trace (same order as the run's traces): float16 keyframe velocities, if needed
    velocities: list[F64 | None]

    def groups(self, methods: Sequence[str]) -> list[tuple[int, bool, list[str]]]:
        """Methods grouped by (frame bytes, needs velocities), in first-seen order."""
        out: dict[tuple[int, bool], list[str]] = {}
        for m in methods:
            key = (self.frame_bytes[m], interp.info(m).needs_velocity)
            out.setdefault(key, []).append(m)
        return [(fb, v, ms) for (fb, v), ms in out.items()]


def _bytes_saving(
    eq: Mapping[str, int | None], soa_rate: int, wire: _Wire
) -> dict[str, float | None]:
    """Each method's bytes/s saving at its equal-QoE rate against SoA at ``soa_rate``."""
    ref = soa_rate * wire.frame_bytes["soa"]
    return {
        m: saving_pct(None if r is None else r * wire.frame_bytes[m], ref) for m, r in eq.items()
    }


def _wire(trs: Sequence[Trace], methods: Sequence[str], room_poses: int) -> _Wire:
    needs = any(interp.info(m).needs_velocity for m in methods)
    return _Wire(
        frame_bytes={m: method_wire_bytes(m, room_poses) for m in methods},
        lookahead={m: interp.info(m).lookahead for m in methods},
        velocities=[keyframe_velocities(tr) if needs else None for tr in trs],
    )


@dataclass
class _Sweep:
    """Pooled and per-trace statistics of one sweep, by rate.

    ``hands_tip`` keeps the pooled hands tip errors (mm) per rate and method,
    for the error-distribution plots (only when asked to). ``network`` is the
    figures of a method without look-ahead on the plain wire variant;
    ``network_by_method`` each method's own (its D includes its look-ahead).
    """

    pooled: dict[int, Stats]
    per_trace: dict[str, dict[int, Stats]]
    network: dict[int, dict[str, float]]
    hands_tip: dict[int, dict[str, F64]]
    network_by_method: dict[int, dict[str, dict[str, float]]] = field(default_factory=dict)


def _sweep(
    traces: Sequence[Trace],
    rates: Sequence[int],
    methods: Sequence[str],
    make_log: _LogMaker,
    tick: Callable[[], None],
    wire: _Wire,
    per_trace_stats: bool = True,
    keep_samples: bool = False,
    finished: dict[int, Stats] | None = None,
) -> _Sweep:
    """Every method at every rate: one log per wire variant, one D per look-ahead.
    ``finished`` gets each rate's pooled statistics as soon as that rate is done
    (what an interrupted run can still report)."""
    pooled: dict[int, Stats] = {}
    per_trace: dict[str, dict[int, Stats]] = {tr.name: {} for tr in traces}
    network: dict[int, dict[str, float]] = {}
    by_method: dict[int, dict[str, dict[str, float]]] = {}
    hands_tip: dict[int, dict[str, F64]] = {}
    for rate in rates:
        groups = []
        nets = {m: _Net() for m in methods}
        for i, tr in enumerate(traces):
            g: dict[str, dict[str, ErrorSamples]] = {}
            for fb, needs_v, ms in wire.groups(methods):
                log, d, window, n = make_log(
                    i, tr, rate, fb, wire.velocities[i] if needs_v else None
                )
                for la in sorted({wire.lookahead[m] for m in ms}):
                    la_ms = [m for m in ms if wire.lookahead[m] == la]
                    g.update(evaluate_group(tr, log, d + la / rate, la_ms, window))
                    for m in la_ms:
                        nets[m].add(replace(n, d_weighted=n.d_weighted + la / rate * n.samples))
            g = {m: g[m] for m in methods}
            groups.append(g)
            if per_trace_stats:
                per_trace[tr.name][rate] = summarize([g])
            tick()
        pooled[rate] = summarize(groups)
        if finished is not None:
            finished[rate] = pooled[rate]
        by_method[rate] = {m: nets[m].summary() for m in methods}
        network[rate] = by_method[rate][methods[0]]
        if keep_samples:
            hands_tip[rate] = {
                m: np.concatenate([x for g in groups for x in g[m]["hands"].tip_mm])
                for m in methods
                if any("hands" in g[m] for g in groups)
            }
    return _Sweep(pooled, per_trace, network, hands_tip, by_method)


def _headline(
    stats: Mapping[int, Stats], method: str, cls: str = HEADLINE[0], key: str = HEADLINE[1]
) -> dict[int, float]:
    """``{rate: stat}`` of one method and device class (default: the headline)."""
    return {r: s[method].get(cls, {}).get(key, float("nan")) for r, s in stats.items()}


def _classes(stats: Mapping[int, Stats]) -> list[str]:
    present = {c for s in stats.values() for classes in s.values() for c in classes}
    return [c for c in ("hands", "head", "objects") if c in present]


def _equal_by_class(
    stats: Mapping[int, Stats], meths: Sequence[str], ref_rate: int, rates: Sequence[int]
) -> dict[str, dict[str, int | None]]:
    """Equal-QoE rates judged on each device class's p95 tip error instead of the hands'."""
    out: dict[str, dict[str, int | None]] = {}
    for cls in _classes(stats):
        curves = {m: _headline(stats, m, cls) for m in meths}
        ref = curves["soa"][ref_rate]
        out[cls] = {m: equal_qoe_rate(curves[m], ref, rates) for m in meths}
    return out


def _curves_json(stats: Mapping[int, Stats], methods: Sequence[str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for m in methods:
        out[m] = {}
        for r in sorted(stats):
            classes = stats[r].get(m, {})
            entry: dict[str, Any] = {}
            for cls, st in classes.items():
                entry[cls] = {k: st[k] for k in (*CURVE_KEYS, "stall_fraction")}
            out[m][str(r)] = entry
    return out


# ---------------------------------------------------------------- (b) ideal network


def ideal_tier_rows(
    tiers: Sequence[Tier],
    soa_rates: Mapping[str, int],
    ideal: _Sweep,
    meths: Sequence[str],
    rate_list: Sequence[int],
    wire: _Wire,
) -> list[dict[str, Any]]:
    """One row per tier: equal-QoE rates and savings on the ideal network (no running time)."""
    heads = {m: _headline(ideal.pooled, m) for m in meths}
    smooth = {m: _headline(ideal.pooled, m, *SMOOTHNESS) for m in meths}
    paper_by_tier = {p["name"]: p for p in PAPER["tiers"]}
    rows: list[dict[str, Any]] = []
    for tier in tiers:
        r_soa = soa_rates[tier.name]
        row = _ideal_tier_row(tier, r_soa, ideal, heads, meths, rate_list, wire)
        row |= _smoothness_columns(r_soa, smooth, meths, rate_list, wire)
        paper = paper_by_tier.get(tier.name)
        if paper is not None:
            row |= _paper_columns(paper, row, heads, smooth, meths)
        row["gain_split"] = gain_split(row, meths)
        rows.append(row)
    return rows


def _smoothness_columns(
    r_soa: int,
    smooth: Mapping[str, Mapping[int, float]],
    meths: Sequence[str],
    rate_list: Sequence[int],
    wire: _Wire,
) -> dict[str, Any]:
    """Equal-smoothness rates: as equal-QoE, judged on the hands' p95 velocity error."""
    ref = smooth["soa"][r_soa]
    eq = {m: equal_qoe_rate(smooth[m], ref, rate_list) for m in meths}
    return {
        "smoothness_reference_mps": ref,
        "equal_smoothness_rate": eq,
        "equal_smoothness_rate_snapped": {m: snapped_range(eq[m], rate_list) for m in meths},
        "smoothness_bandwidth_saving_pct": {m: saving_pct(eq[m], r_soa) for m in meths},
        "smoothness_bytes_saving_pct": _bytes_saving(eq, r_soa, wire),
        "smoothness_at_soa_rate_mps": {m: smooth[m][r_soa] for m in meths},
    }


def _ideal_tier_row(
    tier: Tier,
    r_soa: int,
    ideal: _Sweep,
    heads: Mapping[str, Mapping[int, float]],
    meths: Sequence[str],
    rate_list: Sequence[int],
    wire: _Wire,
) -> dict[str, Any]:
    ref = heads["soa"][r_soa]
    eq = {m: equal_qoe_rate(heads[m], ref, rate_list) for m in meths}
    return {
        "name": tier.name,
        "soa_rate": r_soa,
        "tier": tier.as_dict(),
        "reference_headline_mm": ref,
        "equal_qoe_rate": eq,
        "equal_qoe_rate_snapped": {m: snapped_range(eq[m], rate_list) for m in meths},
        "bandwidth_saving_pct": {m: saving_pct(eq[m], r_soa) for m in meths},
        "bytes_saving_pct": _bytes_saving(eq, r_soa, wire),
        "wire_bytes_per_snapshot": dict(wire.frame_bytes),
        "latency_at_equal_rate_ms": {
            m: (None if (r := eq[m]) is None else ideal.network_by_method[r][m]["latency_ms"])
            for m in meths
        },
        "latency_at_soa_rate_ms": ideal.network_by_method[r_soa]["soa"]["latency_ms"],
        "headline_at_equal_rate_mm": {
            m: (None if (r := eq[m]) is None else heads[m][r]) for m in meths
        },
        "headline_at_soa_rate_mm": {m: heads[m][r_soa] for m in meths},
        "equal_qoe_rate_by_class": _equal_by_class(ideal.pooled, meths, r_soa, rate_list),
        "running_time_saving_pct": dict.fromkeys(meths),
    }


def _paper_columns(
    paper: Mapping[str, Any],
    row: Mapping[str, Any],
    heads: Mapping[str, Mapping[int, float]],
    smooth: Mapping[str, Mapping[int, float]],
    meths: Sequence[str],
) -> dict[str, Any]:
    """The paper's row for a tier, and its GA methods' numbers and verdicts at its rate.

    ``reproduced``: on accuracy (the headline); ``reproduced_smoothness``: on
    smoothness, the paper's own terms (it judged jitter by eye).
    """
    ga = [m for m in meths if m in PAPER["ga_methods"]]
    r_p = paper["ga_rate"]

    def met(key: str) -> dict[str, bool]:
        return {m: ((r := row[key][m]) is not None and r <= r_p) for m in ga}

    return {
        "paper": paper,
        "headline_at_paper_rate_mm": {m: heads[m][r_p] for m in ga},
        "smoothness_at_paper_rate_mps": {m: smooth[m][r_p] for m in ga},
        "reproduced": met("equal_qoe_rate"),
        "reproduced_smoothness": met("equal_smoothness_rate"),
    }


# ---------------------------------------------------------------- (c) through each tier's link


def link_rows(
    trs: Sequence[Trace],
    tiers: Sequence[Tier],
    soa_rates: Mapping[str, int],
    all_rates: Sequence[int],
    rate_list: Sequence[int],
    meths: Sequence[str],
    wire: _Wire,
    *,
    seed: int,
    transport: Transport,
    stage: StageTicks,
) -> tuple[list[dict[str, Any]], dict[str, _Sweep]]:
    """Each tier's rows through its link model, and the sweeps behind them (for the plots)."""
    rows: list[dict[str, Any]] = []
    sweeps: dict[str, _Sweep] = {}
    for ti, tier in enumerate(tiers):
        maker = _link_log_maker(tier, ti, seed, transport)
        r_soa = soa_rates[tier.name]
        # Through the link a method may not exceed the tier's rate: sweep up to it.
        allowed = [r for r in all_rates if r <= r_soa]
        sw = _sweep(trs, allowed, meths, maker, stage(f"link:{tier.name}"), wire, False)
        sweeps[tier.name] = sw
        rows.append(_link_row(tier.name, r_soa, sw, meths, rate_list, wire, transport))
    return rows, sweeps


def _link_row(
    name: str,
    r_soa: int,
    sw: _Sweep,
    meths: Sequence[str],
    rate_list: Sequence[int],
    wire: _Wire,
    transport: Transport,
) -> dict[str, Any]:
    lh = {m: _headline(sw.pooled, m) for m in meths}
    ref = lh["soa"][r_soa]
    eq = {m: equal_qoe_rate(lh[m], ref, rate_list) for m in meths}
    return {
        "name": name,
        "soa_rate": r_soa,
        "transport": transport,
        "playout": "fixed per run: D = 1/rate + p95(arrival - capture)",
        "reference_headline_mm": ref,
        "equal_qoe_rate": eq,
        "equal_qoe_rate_snapped": {m: snapped_range(eq[m], rate_list) for m in meths},
        "bandwidth_saving_pct": {m: saving_pct(eq[m], r_soa) for m in meths},
        "bytes_saving_pct": _bytes_saving(eq, r_soa, wire),
        "at_soa_rate": {m: _link_at(sw, m, r_soa, wire) for m in meths},
        "at_equal_rate": {m: _link_at(sw, m, eq[m], wire) for m in meths},
        "curves": _curves_json(sw.pooled, meths),
        "network": {str(r): sw.network[r] for r in sorted(sw.network)},
    }


def _link_at(sw: _Sweep, m: str, r: int | None, wire: _Wire) -> dict[str, Any] | None:
    """Method ``m`` at rate ``r`` through the link: headline, stalls, bytes/s, network."""
    if r is None:
        return None
    hands = sw.pooled[r][m].get("hands", {})
    head = sw.pooled[r][m].get("head", {})
    return {
        "rate": r,
        "headline_mm": hands.get("tip_p95_mm", float("nan")),
        "head_tip_p95_mm": head.get("tip_p95_mm", float("nan")),
        "stall_fraction": hands.get("stall_fraction", float("nan")),
        "bytes_per_s": float(r * wire.frame_bytes[m]),
        **sw.network_by_method[r][m],
    }


# ---------------------------------------------------------------- per trace


def per_trace_report(
    trs: Sequence[Trace],
    ideal: _Sweep,
    meths: Sequence[str],
    all_rates: Sequence[int],
    rate_list: Sequence[int],
    tiers: Sequence[Tier],
    soa_rates: Mapping[str, int],
) -> dict[str, Any]:
    """Every trace on its own (ideal network): headlines and equal-QoE rates against its SoA."""
    per_trace: dict[str, Any] = {}
    for tr in trs:
        stats = ideal.per_trace[tr.name]
        ph = {m: _headline(stats, m) for m in meths}
        per_trace[tr.name] = {
            "duration_s": tr.duration,
            "native_rate_hz": tr.native_rate,
            "streams": list(tr.streams),
            "headline_mm": {m: {str(r): ph[m][r] for r in all_rates} for m in meths},
            "tip_p95_mm_by_class": {
                cls: {m: {str(r): v for r, v in _headline(stats, m, cls).items()} for m in meths}
                for cls in _classes(stats)
            },
            "equal_qoe_rate": {
                t.name: {
                    m: equal_qoe_rate(ph[m], ph["soa"][soa_rates[t.name]], rate_list) for m in meths
                }
                for t in tiers
            },
            "equal_qoe_rate_by_class": {
                t.name: _equal_by_class(stats, meths, soa_rates[t.name], rate_list) for t in tiers
            },
        }
    return per_trace
