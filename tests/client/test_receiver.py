"""Receiver model: clock estimator, jitter buffer, adaptive delay, batched render."""

from __future__ import annotations

import numpy as np

from posecast.client.buffers import StreamBuffer
from posecast.client.playout import ClockEstimator, PlayoutDelay
from posecast.client.render import render_buffers
from posecast.interp import soa


def _pose(x: float) -> np.ndarray:
    return np.array([x, 0, 0, 1, 0, 0, 0], dtype=np.float32)


def test_clock_estimator_keeps_lowest_rtt_sample() -> None:
    """The offset comes from the sample with the smallest round trip in the window."""
    est = ClockEstimator(window=3)
    est.add(offset=5.0, rtt=0.050)
    est.add(offset=4.2, rtt=0.002)
    est.add(offset=4.9, rtt=0.030)
    assert est.offset == 4.2 and est.rtt == 0.002
    est.add(offset=4.8, rtt=0.010)
    est.add(offset=4.7, rtt=0.020)  # the 2 ms sample has left the window
    assert est.offset == 4.8


def test_buffer_orders_drops_duplicates_and_stale() -> None:
    """Keyframes are kept by capture time; duplicates and ones behind the floor go."""
    buf = StreamBuffer(capacity=3)
    assert buf.push(0.2, _pose(2))
    assert buf.push(0.1, _pose(1))  # out of order: inserted in place
    assert not buf.push(0.2, _pose(9))  # duplicate
    assert not buf.push(0.05, _pose(0), floor=0.15)  # 0.1 already precedes playout
    assert buf.push(0.3, _pose(3))
    assert buf.push(0.4, _pose(4))  # evicts the oldest
    assert buf.times == [0.2, 0.3, 0.4]
    assert (buf.duplicates, buf.stale, buf.evicted) == (1, 1, 1)


def test_late_keyframe_before_playout_is_kept_as_lower_bracket() -> None:
    """A keyframe arriving after playout passed it still brackets if nothing newer did."""
    buf = StreamBuffer()
    buf.push(0.2, _pose(2))
    assert buf.push(0.1, _pose(1), floor=0.15)
    assert buf.bracket(0.15)[:2] == (0, 1)


def test_buffer_bracket_and_hold() -> None:
    """Inside: bracket with fraction; on a keyframe: exact; past the end: hold, stall."""
    buf = StreamBuffer()
    for t in (0.0, 0.1, 0.2):
        buf.push(t, _pose(t))
    lo, hi, s, stall = buf.bracket(0.15)
    assert (lo, hi, stall) == (1, 2, False) and np.isclose(s, 0.5)
    assert buf.bracket(0.1) == (1, 1, 0.0, False)
    assert buf.bracket(0.25) == (2, 2, 0.0, True)
    assert buf.bracket(-1.0) == (2, 2, 0.0, True)  # before all: hold the newest


def test_playout_delay_follows_keyframe_age_smoothly() -> None:
    """D starts at interval + p95 age, then slews toward a new target without jumping."""
    d = PlayoutDelay(interval=0.1, tau=1.0, margin=0.0)
    for _ in range(50):
        d.observe(0.02)
    assert np.isclose(d.update(0.0), 0.12)
    for _ in range(300):
        d.observe(0.08)
    v1 = d.update(0.1)
    assert 0.12 < v1 < 0.18  # moved 10 % of the way
    v2 = d.update(10.0)
    assert np.isclose(v2, 0.18)


def test_render_buffers_is_one_batched_call_matching_pairwise() -> None:
    """Batched render of several buffers equals interpolating each stream alone."""
    bufs = [StreamBuffer() for _ in range(4)]
    for j, buf in enumerate(bufs):
        for t in (0.0, 0.1, 0.2):
            buf.push(t + 0.01 * j, _pose(10 * j + t))
    frame = render_buffers(bufs, 0.125, ["soa", "motor-lerp"])
    assert frame.poses["soa"].shape == (4, 7)
    for j, buf in enumerate(bufs):
        lo, hi, s, _ = buf.bracket(0.125)
        want = soa(buf.poses[lo], buf.poses[hi], s)
        np.testing.assert_allclose(frame.poses["soa"][j], want, atol=1e-12)
    assert not frame.stalled.any()
