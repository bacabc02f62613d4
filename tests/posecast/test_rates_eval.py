"""posecast.rates_eval: auto against fixed rates on an emulated tier, offline and seeded."""

from __future__ import annotations

import math

from posecast.rates_eval import run_link
from posecast.scenarios.network import builtin_tiers, wire_bytes
from posecast.scenarios.traces import DEVICE_NAMES, find_traces, load_trace


def test_auto_fits_the_poor_tier_and_a_fixed_30_overruns_it() -> None:
    """On the poor tier with 16-user snapshots (cap ~15.9 Hz), auto's mean rate settles
    near what the cap carries and skips less than a fixed 30 Hz, which the cap
    clips to its bytes/s; both stay within the cap."""
    trace = load_trace(find_traces("traces:sample")[0]).select(DEVICE_NAMES)
    tier = builtin_tiers()["poor"]
    frame = wire_bytes(48)
    auto = run_link("poor", [tier], math.inf, [trace], "auto", frame)
    fixed = run_link("poor", [tier], math.inf, [trace], "30", frame)
    fits = tier.bytes_per_s / frame
    assert 0.7 * fits <= auto.rate_hz <= 1.1 * fits
    assert fixed.rate_hz == 30.0
    assert auto.bytes_per_s <= tier.bytes_per_s * 1.01
    assert fixed.bytes_per_s <= tier.bytes_per_s * 1.01
    assert auto.hands_stall_pct < fixed.hands_stall_pct
