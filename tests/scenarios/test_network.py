"""Network tiers as data and the seeded link model: cap, delay, jitter, loss, determinism."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from posecast.protocol import frame_size
from posecast.scenarios.network import (
    GAMMA_SHAPE,
    LinkModel,
    Tier,
    TierError,
    affordable_rate,
    builtin_tiers,
    load_tiers,
    wire_bytes,
)


def _tier(**kw: float) -> Tier:
    base = {
        "max_rate_hz": 30.0,
        "bandwidth_kbps": 10_000.0,
        "latency_ms": 40.0,
        "jitter_ms": 10.0,
        "loss_pct": 0.0,
    }
    base.update(kw)
    return Tier(name="test", **base)


def test_builtin_tiers_carry_the_papers_rates() -> None:
    """The four packaged tiers allow 30/20/15/12 updates/s, as in the paper's Table 1."""
    tiers = builtin_tiers()
    assert list(tiers) == ["excellent", "good", "mediocre", "poor"]
    assert [t.max_rate_hz for t in tiers.values()] == [30, 20, 15, 12]
    assert all(t.note.startswith("assumed") for t in tiers.values())


def test_builtin_caps_carry_a_16_user_room_at_the_tier_rate() -> None:
    """Each cap affords the tier's rate for 48-pose snapshots, so the rate, not the cap, binds."""
    for t in builtin_tiers().values():
        assert affordable_rate(t, wire_bytes(48)) == t.max_rate_hz
        assert t.bytes_per_s / wire_bytes(48) >= 1.25 * t.max_rate_hz


def test_user_file_overrides_fields_and_adds_tiers(tmp_path: Path) -> None:
    """load_tiers merges a user's file: same name overrides given fields, new names add tiers."""
    f = tmp_path / "tiers.toml"
    f.write_text(
        "[tier.poor]\nloss_pct = 5.0\n"
        "[tier.satellite]\nmax_rate_hz = 10\nbandwidth_kbps = 100\nlatency_ms = 300\n"
        "jitter_ms = 20\nloss_pct = 1\n"
    )
    tiers = load_tiers(f)
    assert list(tiers) == ["excellent", "good", "mediocre", "poor", "satellite"]
    assert tiers["poor"].loss_pct == 5.0 and tiers["poor"].latency_ms == 90.0
    assert tiers["satellite"].latency_ms == 300.0


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[tier.new]\nmax_rate_hz = 10\n", "new tier needs"),
        ("[tier.poor]\nlatency = 5\n", "unknown field"),
        ("[tier.poor]\nloss_pct = 100\n", "loss_pct"),
        ("[tier.poor]\njitter_ms = 80\n", "sqrt"),
        ("[tier.poor]\nmax_rate_hz = 'fast'\n", "must be a number"),
        ("not toml [", "not valid TOML"),
    ],
)
def test_bad_tier_files_are_refused_with_the_reason(
    tmp_path: Path, text: str, message: str
) -> None:
    """Missing fields, unknown fields and impossible values name the file and the problem."""
    f = tmp_path / "tiers.toml"
    f.write_text(text)
    with pytest.raises(TierError, match=message):
        load_tiers(f)


def test_affordable_rate_is_the_smaller_of_rate_and_cap() -> None:
    """affordable_rate = min(max rate, cap / frame bytes)."""
    t = _tier(bandwidth_kbps=80.0)  # 10 000 B/s
    assert affordable_rate(t, 100) == 30.0
    assert affordable_rate(t, 1000) == pytest.approx(10.0)


def test_wire_bytes_add_websocket_and_tcp_ip_headers() -> None:
    """A snapshot on the wire is its frame plus a websocket header plus 52 B per TCP segment."""
    assert wire_bytes(1) == frame_size(1) + 2 + 52  # under 126 B: 2-byte ws header
    assert wire_bytes(3) == frame_size(3) + 4 + 52
    assert wire_bytes(48) == frame_size(48) + 4 + 2 * 52  # 1780 B payload: two segments


def test_cap_holds_when_offered_more() -> None:
    """Offered twice the cap for 60 s, the link carries the cap within 5 % and skips the rest."""
    tier = _tier(bandwidth_kbps=80.0)  # 10 000 B/s
    send = np.arange(0, 60, 1 / 20)  # 20 frames/s x 1000 B = 20 000 B/s
    d = LinkModel(tier, seed=1).transmit(send, 1000)
    assert d.sent_bytes_per_s() == pytest.approx(tier.bytes_per_s, rel=0.05)
    assert d.sent_bytes_per_s() <= tier.bytes_per_s * 1.01
    assert 0.4 < d.skipped.mean() < 0.6
    # Latest wins: nothing waits longer than one send interval, so no queue builds up.
    wait = (d.departure - d.send)[~d.skipped]
    assert wait.max() <= 1 / 20 + 1e-12


def test_below_the_cap_nothing_waits_or_is_skipped() -> None:
    """Offered less than the cap, every frame departs when sent."""
    tier = _tier(bandwidth_kbps=800.0)
    send = np.arange(0, 10, 1 / 30)
    d = LinkModel(tier).transmit(send, 1000)  # 30 000 B/s < 100 000 B/s
    assert not d.skipped.any()
    np.testing.assert_array_equal(d.departure, send)


def test_delay_and_jitter_follow_the_tier() -> None:
    """One-way delays have the tier's mean and standard deviation and the documented floor."""
    tier = _tier(latency_ms=40.0, jitter_ms=10.0)
    send = np.arange(20_000) / 30.0
    delay = LinkModel(tier, seed=3).transmit(send, 200).delay
    n = delay.size
    assert abs(delay.mean() - 0.040) < 4 * 0.010 / math.sqrt(n)
    assert delay.std() == pytest.approx(0.010, rel=0.05)
    assert delay.min() >= 0.040 - math.sqrt(GAMMA_SHAPE) * 0.010 - 1e-12
    assert np.median(delay) < delay.mean()  # right-skewed
    zero = LinkModel(_tier(jitter_ms=0.0), seed=3).transmit(send, 200).delay
    np.testing.assert_allclose(zero, 0.040)


def test_loss_fraction_follows_the_tier() -> None:
    """Each frame is lost with probability loss_pct; lost frames never arrive (NaN)."""
    tier = _tier(loss_pct=5.0)
    send = np.arange(20_000) / 30.0
    d = LinkModel(tier, seed=4).transmit(send, 200)
    se = math.sqrt(0.05 * 0.95 / send.size)
    assert abs(d.lost.mean() - 0.05) < 4 * se
    assert np.all(np.isnan(d.arrival[d.lost])) and np.all(np.isfinite(d.arrival[~d.lost]))


def test_same_seed_same_delivery() -> None:
    """A link model is deterministic for a seed, and different seeds differ."""
    tier = _tier(loss_pct=2.0, bandwidth_kbps=100.0)
    send = np.arange(0, 30, 1 / 25)
    a = LinkModel(tier, seed=9).transmit(send, 700)
    b = LinkModel(tier, seed=9).transmit(send, 700)
    c = LinkModel(tier, seed=10).transmit(send, 700)
    np.testing.assert_array_equal(a.arrival, b.arrival)
    np.testing.assert_array_equal(a.skipped, b.skipped)
    assert not np.array_equal(a.arrival, c.arrival, equal_nan=True)


def test_stream_transport_delivers_everything_in_order() -> None:
    """TCP-like transport: lost frames come late (one RTO or more), never out of order."""
    tier = _tier(loss_pct=5.0)
    send = np.arange(0, 60, 1 / 30)
    link = LinkModel(tier, seed=2, transport="stream")
    d = link.transmit(send, 300)
    assert np.all(np.isfinite(d.arrival)) and not d.lost.any()
    assert np.all(np.diff(d.arrival) >= 0)
    assert d.delay.max() >= link.rto
    assert link.rto == pytest.approx(max(0.2, 0.080 + 4 * math.sqrt(2) * 0.010))


def test_transmit_refuses_unordered_send_times() -> None:
    """Send times must not go backwards; sizes must be positive."""
    link = LinkModel(replace(builtin_tiers()["good"]))
    with pytest.raises(ValueError, match="non-decreasing"):
        link.transmit([0.0, 1.0, 0.5], 100)
    with pytest.raises(ValueError, match="positive"):
        link.transmit([0.0, 1.0], 0)
