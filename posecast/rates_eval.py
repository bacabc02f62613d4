"""Auto rates judged against fixed rates on Table 1's links (``python -m posecast.rates_eval``).

For every link (each tier of ``scenarios/data/tiers.toml``, and one that switches
tiers every ``switch_s`` seconds) and every policy (each fixed rate of ``rates``,
and ``auto``: the relay's own :class:`server.rates.LinkRate`), one subscriber
receives every eval trace as a peer's streams, in snapshots the size of a
``room``-user raw room (16 users: 1,884 wire bytes, the size the tiers' bandwidth
was chosen for), through the relay's own emulated egress
(:class:`server.link.EgressLink`: token-bucket cap, skewed delay, loss). A fixed
policy ticks at its rate whatever the link (the cap skips what does not fit);
``auto`` ticks at the rate its controller chooses from what the relay sees (the
cap's skips and the bytes that got through; never the tier). The receiver
renders with SoA at a playout delay D it sets from what arrived: 1/rate in force
plus the 95th percentile of the keyframe ages of the last 5 s (once per 0.5 s).
QoE is scored with :func:`scenarios.qoe.evaluate_group` (DESIGN.md's definitions;
a stalled sample shows the held pose and counts in the error and the stall share).

Everything is seeded and offline (no sockets, no clocks): the figures do not
depend on how loaded the machine is. The live relay runs the same controller
and the same link model (``tests/server/test_rates_relay.py``).
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from posecast.scenarios.network import Tier, builtin_tiers, wire_bytes
from posecast.scenarios.qoe import KeyframeLog, evaluate_group, summarize
from posecast.scenarios.traces import DEVICE_NAMES, Trace, find_traces, load_trace
from posecast.server.link import EgressLink
from posecast.server.rates import Egress, LinkRate

__all__ = ["Run", "main", "run_link"]

F64 = NDArray[np.float64]
AGE_WINDOW_S = 5.0
D_EVERY_S = 0.5


@dataclass
class Run:
    """What one policy got on one link, over every trace."""

    link: str
    policy: str
    hands_tip_p95_mm: float
    hands_stall_pct: float
    delay_ms: float
    bytes_per_s: float
    rate_hz: float


class SwitchingLink:
    """An :class:`EgressLink` whose tier changes every ``period`` s (cycling ``tiers``)."""

    def __init__(self, tiers: Sequence[Tier], period: float, seed: int) -> None:
        self.tiers, self.period, self.seed = list(tiers), period, seed
        self._i = -1
        self.link = EgressLink(self.tiers[0], seed)
        self.bytes = self.cap_skips = 0

    def offer(self, now: float, t0: float, size: int) -> float | None:
        i = int((now - t0) // self.period)
        if i != self._i:  # a new tier: its own bucket and delay
            self._i = i
            self.link = EgressLink(self.tiers[i % len(self.tiers)], self.seed * 1000 + i)
        skips = self.link.cap_skips
        arrival = self.link.offer(now, size)
        self.cap_skips += self.link.cap_skips - skips
        if arrival is not None:
            self.bytes += size
        return arrival


def _transmit(
    trace: Trace, link: SwitchingLink, policy: str, frame: int
) -> tuple[KeyframeLog, F64, F64]:
    """Send ``trace`` through ``link``; the keyframes that arrived, and the (time, rate)
    steps of the rate in force."""
    times, t0 = trace.times, float(trace.times[0])
    ctl = LinkRate(5.0, 30.0) if policy == "auto" else None
    rate = 30.0 if ctl is not None else float(policy)
    t, ticks = t0, 0
    caps: list[float] = []
    arrivals: list[float] = []
    idxs: list[int] = []
    steps_t, steps_r = [t0], [rate]
    last = -1
    while t <= times[-1]:
        i = int(np.searchsorted(times, t, side="right")) - 1
        if i != last:  # a new keyframe (the relay sends nothing unchanged)
            last = i
            ticks += 1
            arrival = link.offer(t, t0, frame)
            if arrival is not None:
                caps.append(float(times[i]))
                arrivals.append(arrival)
                idxs.append(i)
        if ctl is not None:
            new = ctl.update(t, Egress(ticks, link.cap_skips, link.bytes))
            if new is not None:
                rate = new
                steps_t.append(t)
                steps_r.append(rate)
        t += 1.0 / rate
    log = KeyframeLog(np.array(caps), np.array(arrivals), trace.poses[np.array(idxs)])
    return log, np.array(steps_t), np.array(steps_r)


def _delay_fn(log: KeyframeLog, steps_t: F64, steps_r: F64, native: float) -> Any:
    """D(tau): 1/rate in force + p95 of the ages of the keyframes that arrived in the
    last AGE_WINDOW_S, updated every D_EVERY_S (a receiver's choice, causal)."""
    ages = log.arrival - log.capture
    order = np.argsort(log.arrival)
    arr, ages = log.arrival[order], ages[order]

    def delay(taus: F64) -> F64:
        grid = np.floor(taus / D_EVERY_S) * D_EVERY_S
        out = np.empty_like(taus)
        cache: dict[float, float] = {}
        for k, g in enumerate(grid):
            d = cache.get(g)
            if d is None:
                lo, hi = np.searchsorted(arr, [g - AGE_WINDOW_S, g])
                p95 = float(np.percentile(ages[lo:hi], 95)) if hi - lo >= 3 else 0.1
                rate = float(steps_r[np.searchsorted(steps_t, g, side="right") - 1])
                d = cache[g] = 1.0 / rate + p95 + 1.0 / native
            out[k] = d
        return out

    return delay


def run_link(
    name: str,
    tiers: Sequence[Tier],
    period: float,
    traces: Sequence[Trace],
    policy: str,
    frame: int,
) -> Run:
    """One policy on one link over every trace (pooled)."""
    groups, d_sum, n_d, bytes_, span, rate_time = [], 0.0, 0, 0, 0.0, 0.0
    for k, tr in enumerate(traces):
        link = SwitchingLink(tiers, period, seed=k + 1)
        log, steps_t, steps_r = _transmit(tr, link, policy, frame)
        delay = _delay_fn(log, steps_t, steps_r, tr.native_rate)
        groups.append(evaluate_group(tr, log, delay, ["soa"]))
        taus = tr.times[(tr.times >= log.capture[0]) & (tr.times <= log.capture[-1])]
        d_sum += float(np.sum(delay(taus)))
        n_d += taus.size
        dur = float(tr.times[-1] - tr.times[0])
        bytes_ += link.bytes
        span += dur
        ends = np.append(steps_t[1:], tr.times[-1])
        rate_time += float(np.sum(steps_r * (ends - steps_t)))
    hands = summarize(groups)["soa"]["hands"]
    return Run(
        name,
        policy,
        hands["tip_p95_mm"],
        100.0 * hands["stall_fraction"],
        1000.0 * d_sum / max(1, n_d),
        bytes_ / span,
        rate_time / span,
    )


def _table(runs: list[Run]) -> str:
    lines = [
        "| link | policy | hands tip p95 mm | stall % | D ms | kB/s | mean rate Hz |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in runs:
        lines.append(
            f"| {r.link} | {r.policy} | {r.hands_tip_p95_mm:.1f} | {r.hands_stall_pct:.2f} | "
            f"{r.delay_ms:.0f} | {r.bytes_per_s / 1000:.1f} | {r.rate_hz:.1f} |"
        )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m posecast.rates_eval", description=__doc__)
    ap.add_argument("--traces", default="traces:eval")
    ap.add_argument("--rates", default="5,10,15,20,25,30")
    ap.add_argument("--room", type=int, default=16, help="users whose poses a snapshot holds")
    ap.add_argument("--switch-s", type=float, default=20.0)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    traces = [load_trace(p).select(DEVICE_NAMES) for p in find_traces(args.traces)]
    frame = wire_bytes(3 * args.room)
    tiers = builtin_tiers()
    links: list[tuple[str, list[Tier]]] = [(n, [t]) for n, t in tiers.items()]
    order = ["excellent", "poor", "good", "mediocre"]
    links.append(("switching", [tiers[n] for n in order if n in tiers]))
    policies = [*args.rates.split(","), "auto"]
    runs = [
        run_link(name, ts, args.switch_s if len(ts) > 1 else math.inf, traces, p, frame)
        for name, ts in links
        for p in policies
    ]
    print(f"{len(traces)} traces ({args.traces}), {args.room}-user raw snapshots ({frame} B)")
    print(_table(runs))
    if args.json:
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump([r.__dict__ for r in runs], f, indent=1)


if __name__ == "__main__":
    main()
