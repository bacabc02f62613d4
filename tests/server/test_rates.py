"""server.rates: the auto rate controller against simulated links, time injected."""

from __future__ import annotations

import itertools
import math

import pytest

from posecast.protocol import Join
from posecast.server.rates import Egress, LinkRate, RateHistogram, granted


class CappedLink:
    """A subscriber's egress through a byte-rate cap (a deficit token bucket, as
    ``server.link.EgressLink``): latest-wins, a frame that finds the bucket in deficit
    is skipped. Cumulative counters as the relay keeps them."""

    def __init__(self, bytes_per_s: float, frame: int = 1000) -> None:
        self.cap, self.frame = bytes_per_s, frame
        self.tokens, self.t = 0.05 * bytes_per_s, 0.0
        self.ticks = self.skips = self.drained = 0

    def offer(self, now: float) -> None:
        self.tokens = min(0.05 * self.cap, self.tokens + (now - self.t) * self.cap)
        self.t = now
        self.ticks += 1
        if self.tokens < 0:
            self.skips += 1
            return
        self.tokens -= self.frame
        self.drained += self.frame

    def egress(self) -> Egress:
        return Egress(self.ticks, self.skips, self.drained)


def run(ctl: LinkRate, link: CappedLink, start: float, until: float) -> list[tuple[float, float]]:
    """Tick the subscriber on its own grid until ``until``, the controller deciding after
    every tick as the relay does; returns (time, rate) of each change."""
    changes: list[tuple[float, float]] = []
    t = start
    while t < until:
        link.offer(t)
        new = ctl.update(t, link.egress())
        if new is not None:
            changes.append((t, new))
        t += 1.0 / ctl.rate
    return changes


def test_a_wide_link_keeps_the_ceiling_without_a_change() -> None:
    """A link that carries max_rate: the controller starts there and never moves."""
    ctl = LinkRate(5.0, 30.0)
    link = CappedLink(100_000)  # 100 kB/s for 30 kB/s of snapshots
    assert run(ctl, link, 0.0, 60.0) == []
    assert ctl.rate == 30.0 and link.skips == 0


def test_a_narrow_link_brings_the_rate_down_within_a_window() -> None:
    """At 30 Hz through 15 kB/s of 1 kB frames, the first window with skips brings the
    rate down at once to what the drain carries with headroom (<= 0.95 x 15 Hz)."""
    ctl = LinkRate(5.0, 30.0)
    link = CappedLink(15_000)
    changes = run(ctl, link, 0.0, 2.0)
    assert changes, "no step down"
    t, rate = changes[0]
    assert t <= 2 * ctl.window + 1e-9
    assert 5.0 <= rate <= ctl.headroom * 15 + 1e-9


def test_on_a_steady_link_it_settles_at_the_cap_and_probes_rarely() -> None:
    """Over two minutes on a 15 kB/s link (15 Hz of 1 kB frames), after settling, it
    delivers over 90 % of what the link carries, skips under 3 % of its ticks, and
    probes above the rate that fits a few times per ceiling_hold (back at once)."""
    ctl = LinkRate(5.0, 30.0)
    link = CappedLink(15_000)
    changes = run(ctl, link, 0.0, 20.0)
    ticks0, skips0 = link.ticks, link.skips
    later = run(ctl, link, 20.0, 140.0)
    delivered = (link.ticks - link.skips) - (ticks0 - skips0)
    assert delivered / 120.0 > 0.9 * 15.0
    assert (link.skips - skips0) / (link.ticks - ticks0) < 0.03
    probes = [r for _, r in later if r > 15.0]
    assert 1 <= len(probes) <= 3 * (120.0 / ctl.ceiling_hold + 1)
    assert changes[0][1] < 15.0 and 14.0 <= ctl.rate <= 16.0


def test_a_lone_skip_at_the_links_edge_keeps_the_rate() -> None:
    """At 20 Hz through a link that carries 19.8 Hz of 1 kB frames, a skip comes about
    every 5 s: each is the link's edge, not congestion. The rate stays at 20 Hz (as the
    best fixed rate would), with no probe above it while the skips keep coming."""
    ctl = LinkRate(5.0, 30.0, start=20.0)
    link = CappedLink(19_800)
    run(ctl, link, 0.0, 10.0)  # its first probe above 20 Hz fails and comes back
    assert ctl.rate == 20.0
    edges, congestions = ctl.edges, ctl.congestions
    assert run(ctl, link, 10.0, 70.0) == [] and ctl.rate == 20.0
    assert ctl.edges - edges >= 5 and ctl.congestions == congestions


def test_after_a_failed_probe_it_waits_and_steps_halfway() -> None:
    """A probe that fails at once goes back, then no step up for ceiling_hold; the
    next probe steps halfway to the rate that failed, not a quarter up again."""
    ctl = LinkRate(5.0, 30.0, start=16.0)
    link = CappedLink(16_500)  # 16.5 Hz of 1 kB frames
    changes = run(ctl, link, 0.0, 40.0)
    (t_up, probe), (t_back, back) = changes[:2]
    assert probe == 20.0 and back == 16.0 and t_back - t_up <= 2 * ctl.up_every + 1e-9
    t_next, nxt = changes[2]
    assert t_next - t_back >= ctl.ceiling_hold - 1e-9
    assert nxt == 18.0  # halfway from 16 to 20


def test_up_slowly_when_the_link_widens() -> None:
    """The link widens from 8 to 40 kB/s: the rate climbs back to 30 Hz, never by more
    than up_step (>= 1 Hz) a step and at least up_every apart."""
    ctl = LinkRate(5.0, 30.0)
    link = CappedLink(8_000)
    run(ctl, link, 0.0, 15.0)
    assert ctl.rate <= 8.0
    link.cap = 40_000
    ups = run(ctl, link, 15.0, 60.0)
    assert ctl.rate == 30.0
    rates = [r for _, r in ups]
    assert rates == sorted(rates)
    prev = None
    for (t0, r0), (t1, r1) in itertools.pairwise(ups):
        assert r1 - r0 <= max(1.0, math.floor(ctl.up_step * r0)) + 1e-9
        assert t1 - t0 >= ctl.up_every - 1e-9
        prev = r1
    assert prev == 30.0


def test_down_fast_when_the_link_narrows() -> None:
    """From 30 Hz at 40 kB/s to a 6 kB/s link: under 1.5 s later the rate fits (<= 6 Hz)."""
    ctl = LinkRate(5.0, 30.0)
    link = CappedLink(40_000)
    run(ctl, link, 0.0, 10.0)
    link.cap = 6_000
    changes = run(ctl, link, 10.0, 11.5)
    assert changes and ctl.rate <= 6.0


def test_a_backlog_is_congestion_without_skips() -> None:
    """A socket whose write buffer holds more than backlog_frames snapshots is congested
    even before a snapshot is skipped: the drain decides the new rate."""
    ctl = LinkRate(5.0, 30.0)
    assert ctl.update(0.0, Egress(0, 0, 0)) is None
    assert ctl.update(0.5, Egress(15, 0, 15_000, backlog=0)) is None  # 1 kB frames
    new = ctl.update(1.0, Egress(30, 0, 20_000, backlog=10_000))  # 10 kB/s drained
    assert new is not None and new <= ctl.headroom * 10_000 / ctl.frame_bytes  # type: ignore[operator]


def test_rates_stay_whole_and_within_the_range() -> None:
    """Every rate chosen is whole Hz in [lo, hi], even on a link that carries nothing."""
    ctl = LinkRate(5.0, 24.0)
    link = CappedLink(500)
    for _, rate in run(ctl, link, 0.0, 30.0):
        assert 5.0 <= rate <= 24.0 and rate == math.floor(rate)
    assert ctl.rate == 5.0


def test_counters_that_restart_are_a_new_baseline() -> None:
    """Counters that went down (a resumed connection's) start a new window, no decision."""
    ctl = LinkRate(5.0, 30.0)
    ctl.update(0.0, Egress(100, 0, 100_000))
    assert ctl.update(1.0, Egress(3, 3, 0)) is None
    assert ctl.rate == 30.0


def test_bad_range_is_refused() -> None:
    """lo must be positive and not above hi."""
    with pytest.raises(ValueError, match="0 < lo <= hi"):
        LinkRate(10.0, 5.0)


def test_granted_rate_of_a_join() -> None:
    """A fixed join gets its rate; an auto join starts at its max_rate, else the server's."""
    fixed = Join(room="r", streams=("head",), rate=12.0)
    assert granted(30.0, fixed) == 12.0
    assert granted(30.0, Join(room="r", streams=("head",), rate="auto")) == 30.0
    assert granted(30.0, Join(room="r", streams=("head",), rate="auto", max_rate=20.0)) == 20.0


def test_histogram_of_chosen_rates() -> None:
    """Observations land in the bucket of their rate; the text is cumulative."""
    hist = RateHistogram()
    for rate in (5.0, 12.0, 30.0, 30.0):
        hist.observe(rate)
    text = "\n".join(hist.metric_lines(members=2))
    assert 'posecast_auto_rate_hz_bucket{le="5"} 1' in text
    assert 'posecast_auto_rate_hz_bucket{le="12.5"} 2' in text
    assert 'posecast_auto_rate_hz_bucket{le="+Inf"} 4' in text
    assert "posecast_auto_rate_hz_sum 77" in text and "posecast_auto_rate_members 2" in text


def test_a_late_relay_steps_the_rate_down_with_no_skip_and_up_once_it_keeps_up() -> None:
    """The relay itself late (its rooms grew past what it carries): down fast, to what
    got through, as for congestion, though the link skipped nothing; at most one step
    per two windows; once the relay keeps up, up slowly again."""
    ctl = LinkRate(5.0, 30.0)
    link = CappedLink(1_000_000)
    t, changes = 0.0, []
    while t < 10.0:
        link.offer(t)
        # Late from 2 s to 5 s: the relay skips grid points (2 of every 3 ticks run).
        late = 2.0 <= t < 5.0
        new = ctl.update(t, link.egress(), relay_late=late)
        if new is not None:
            changes.append((t, new, late))
        t += 1.0 / ctl.rate * (1.5 if late else 1.0)
    assert link.skips == 0
    downs = [(t, r) for t, r, late in changes if late]
    assert downs and all(b[1] < a[1] for a, b in itertools.pairwise([(0.0, 30.0), *downs]))
    assert all(t1 - t0 >= 2 * ctl.window - 1e-9 for (t0, _), (t1, _) in itertools.pairwise(downs))
    lowest = downs[-1][1]
    ups = [(t, r) for t, r, late in changes if not late and t >= 5.0]
    assert ups and ups[-1][1] > lowest
    assert all(r == math.floor(r) and 5.0 <= r <= 30.0 for _, r, _ in changes)


def test_a_late_relay_is_no_lone_skip_at_the_links_edge() -> None:
    """A lone skip keeps the rate (the link's edge); the same window with the relay late
    is a step down."""
    for late, stays in ((False, True), (True, False)):
        ctl = LinkRate(5.0, 30.0)
        assert ctl.update(0.0, Egress(0, 0, 0)) is None
        assert ctl.update(0.5, Egress(15, 0, 15_000)) is None
        new = ctl.update(1.0, Egress(30, 1, 29_000), relay_late=late)
        assert (new is None) == stays, late
