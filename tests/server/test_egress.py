"""EgressLink: the live, frame-by-frame link of a tier (time passed in)."""

from __future__ import annotations

import numpy as np
import pytest

from posecast.scenarios import network
from posecast.scenarios.network import Tier
from posecast.server.link import GAMMA_SHAPE, EgressLink


def _tier(**kw: float) -> Tier:
    fields = {
        "max_rate_hz": 30.0,
        "bandwidth_kbps": 80.0,
        "latency_ms": 40.0,
        "jitter_ms": 10.0,
        "loss_pct": 0.0,
    }
    fields.update(kw)
    return Tier(name="t", **fields)  # type: ignore[arg-type]


def test_cap_holds_when_offered_more() -> None:
    """Offered 3x the cap, the bytes let through stay within 5 % of the cap."""
    tier = _tier(bandwidth_kbps=80.0)  # 10,000 bytes/s
    link = EgressLink(tier, seed=1)
    size, rate, seconds = 500, 60.0, 20.0
    for k in range(int(rate * seconds)):
        link.offer(k / rate, size)
    assert link.bytes / seconds == pytest.approx(tier.bytes_per_s, rel=0.05)
    assert link.cap_skips > 0


def test_delay_and_jitter_follow_the_tier() -> None:
    """One-way delays average the tier's latency, never below latency - sqrt(2) jitter."""
    tier = _tier(bandwidth_kbps=10_000.0, latency_ms=40.0, jitter_ms=10.0)
    link = EgressLink(tier, seed=2)
    delays = np.array([link.offer(k / 30.0, 300) - k / 30.0 for k in range(3000)])  # type: ignore[operator]
    assert delays.mean() == pytest.approx(0.040, abs=0.002)
    assert delays.std() == pytest.approx(0.010, rel=0.15)
    assert delays.min() >= 0.040 - np.sqrt(2) * 0.010 - 1e-12


def test_loss_fraction_and_rate_for() -> None:
    """Loss matches the tier; rate_for caps the asked rate by tier and bandwidth."""
    tier = _tier(bandwidth_kbps=80.0, loss_pct=10.0)
    link = EgressLink(tier, seed=3)
    for k in range(4000):
        link.offer(k * 0.1, 100)  # well under the cap
    assert link.lost / 4000 == pytest.approx(0.10, abs=0.015)
    assert link.rate_for(30.0) == pytest.approx(30.0)  # 100 B frames: the tier's 30 Hz binds
    big = EgressLink(tier, seed=3)
    big.offer(0.0, 1000)
    assert big.rate_for(30.0) == pytest.approx(10.0)  # 10,000 B/s / 1000 B
    assert big.rate_for(5.0) == 5.0


def test_the_live_link_draws_the_offline_models_delays() -> None:
    """The relay's link and the offline LinkModel share one delay distribution."""
    assert GAMMA_SHAPE == network.GAMMA_SHAPE
