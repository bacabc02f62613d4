"""QoE definitions: keyframe sampling, playout brackets, stalls, statistics."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from posecast.scenarios.compare import compare_trace
from posecast.scenarios.qoe import (
    KeyframeLog,
    evaluate_group,
    ideal_delay,
    playout_brackets,
    sample_keyframes,
)
from posecast.scenarios.traces import Trace, load_trace


def _line_trace(n: int = 91, rate: float = 90.0) -> Trace:
    """Head moving at 1 m/s along x with a fixed orientation."""
    t = np.arange(n) / rate
    poses = np.zeros((n, 1, 7))
    poses[:, 0, 0] = t
    poses[:, 0, 3] = 1.0
    return Trace("line", t, poses, ("head",))


def test_sample_keyframes_takes_latest_native_sample() -> None:
    """Each send time t0 + k/r maps to the newest native sample at or before it."""
    times = np.arange(0, 1.0001, 1 / 90)
    send, idx = sample_keyframes(times, 10.0)
    assert np.allclose(send, np.arange(11) / 10)
    assert np.all(times[idx] <= send + 1e-12)
    assert np.all(send - times[idx] < 1 / 90)


def test_sample_keyframes_above_native_rate_dedupes() -> None:
    """A send rate above the native rate never sends the same sample twice."""
    times = np.arange(0, 1.0, 1 / 10)
    _, idx = sample_keyframes(times, 30.0)
    assert np.all(np.diff(idx) > 0)


def test_linear_motion_is_reconstructed_exactly_on_ideal_link() -> None:
    """Constant-velocity translation is exact for every method; no stalls."""
    tr = _line_trace()
    send, idx = sample_keyframes(tr.times, 10.0)
    log = KeyframeLog(tr.times[idx], send, tr.poses[idx])
    res = evaluate_group(tr, log, ideal_delay(10.0, 90.0), ["soa", "dq-slerp", "motor-lerp"])
    for classes in res.values():
        st = classes["head"].stats()
        assert st["pos_p95_mm"] < 1e-9
        assert st["stall_fraction"] == 0.0


def test_late_keyframe_causes_stall_and_hold() -> None:
    """A keyframe arriving after tau + D cannot be used: tau stalls and holds."""
    capture = np.array([0.0, 0.1, 0.2])
    arrival = np.array([0.0, 0.5, 0.2])  # keyframe 1 is very late
    q = np.array([0.05, 0.15])
    play = playout_brackets(capture, arrival, q, delay=0.2)
    # tau = 0.05: deadline 0.25, keyframe 1 missing and 2 arrived: bracket 0..2
    assert (play.lo[0], play.hi[0]) == (0, 2) and not play.stall[0]
    assert np.isclose(play.s[0], 0.25)
    # tau = 0.15: deadline 0.35, lo = keyframe 0 (1 not arrived), hi = 2
    assert (play.lo[1], play.hi[1]) == (0, 2) and not play.stall[1]
    # With D = 0.1, tau = 0.05 has only keyframe 0 by 0.15: a stall holding it.
    late = playout_brackets(capture, arrival, q[:1], delay=0.1)
    assert late.stall[0] and late.lo[0] == late.hi[0] == 0


def test_nothing_after_tau_is_a_stall_holding_newest() -> None:
    """With no later keyframe arrived, the newest arrived is held and counted."""
    capture = np.array([0.0, 0.1])
    arrival = np.array([0.05, 0.5])
    play = playout_brackets(capture, arrival, np.array([0.05, -1.0]), delay=0.01)
    assert play.stall[0] and play.lo[0] == play.hi[0] == 0 and play.s[0] == 0
    assert play.missing[1] and play.stall[1]


def test_query_on_arrived_keyframe_is_not_a_stall() -> None:
    """A sample exactly at an arrived keyframe's capture needs no second keyframe."""
    play = playout_brackets(np.array([0.0, 0.1]), np.array([0.0, 0.1]), np.array([0.1]), 0.0)
    assert not play.stall[0] and play.lo[0] == 1 and play.s[0] == 0


def test_compare_on_real_trace_improves_with_rate(dev_trace_path: Path) -> None:
    """On a real trace the hands' p95 tip error falls as the send rate rises."""
    tr = load_trace(dev_trace_path).window(0.0, 20.0)
    res = compare_trace(tr, [5.0, 15.0, 30.0], ["soa", "motor-lerp"])
    for m in ("soa", "motor-lerp"):
        tips = [res[r][m]["hands"]["tip_p95_mm"] for r in (5.0, 15.0, 30.0)]
        assert tips[0] > tips[1] > tips[2] > 0
        assert res[30.0][m]["hands"]["stall_fraction"] == 0.0
    assert set(res[5.0]["soa"]) == {"hands", "head"}
