"""The velocity error (smoothness) of DESIGN.md: the tip's velocity from differences
over consecutive source sample times, rendered against true, in m/s."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray

from posecast.scenarios.compare import compare_trace
from posecast.scenarios.qoe import (
    STAT_KEYS,
    ErrorSamples,
    KeyframeLog,
    evaluate_group,
    summarize,
    tip_velocity_error_mps,
)
from posecast.scenarios.traces import Trace, load_trace

F64 = NDArray[np.float64]

IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])
#: 90 degrees about x: the tip (0, 0, -0.2) goes to (0, 0.2, 0).
QUARTER_X = np.array([math.sqrt(0.5), math.sqrt(0.5), 0.0, 0.0])


def _poses(xs: list[float], quats: list[F64]) -> F64:
    """One stream ``(Q, 1, 7)`` at ``(x, 0, 0)`` with the given rotations."""
    out = np.zeros((len(xs), 1, 7))
    out[:, 0, 0] = xs
    out[:, 0, 3:] = quats
    return out


def hand_example() -> tuple[F64, F64, F64]:
    """A known rendered and true trajectory (times 0, 0.1, 0.3, 0.4).

    Truth: x = 0, 0.1, 0.3, 0.4, no rotation: the tip moves at (1, 0, 0) m/s.
    Rendered: x = 0, 0.2, 0.3, 0.3, the last one turned 90 degrees about x.
    Tip velocities rendered: (2, 0, 0); (0.5, 0, 0); ((0, 0.2, 0) - (0, 0, -0.2)) / 0.1
    = (0, 2, 2). Errors: |(1, 0, 0)| = 1; |(-0.5, 0, 0)| = 0.5; |(-1, 2, 2)| = 3.
    """
    times = np.array([0.0, 0.1, 0.3, 0.4])
    truth = _poses([0.0, 0.1, 0.3, 0.4], [IDENTITY] * 4)
    rendered = _poses([0.0, 0.2, 0.3, 0.3], [IDENTITY, IDENTITY, IDENTITY, QUARTER_X])
    return times, truth, rendered


def test_velocity_error_matches_a_hand_computation() -> None:
    times, truth, rendered = hand_example()
    err = tip_velocity_error_mps(rendered, truth, times)
    assert err.shape == (3, 1)
    np.testing.assert_allclose(err[:, 0], [1.0, 0.5, 3.0], rtol=0, atol=1e-12)
    samples = ErrorSamples()
    samples.add(np.zeros(4), np.zeros(4), np.zeros(4), 0, 4, vel=err[:, 0])
    st = samples.stats()
    # numpy's linear percentiles of (0.5, 1, 3): p50 = 1, p95 = 1 + 0.9 * 2 = 2.8.
    assert st["vel_p50_mps"] == pytest.approx(1.0, abs=1e-12)
    assert st["vel_p95_mps"] == pytest.approx(2.8, abs=1e-12)


def test_velocity_error_only_pairs_consecutive_shown_samples() -> None:
    """Rendered rows are the shown samples; a pair with an unshown sample is skipped."""
    times, truth, rendered = hand_example()
    late = np.array([False, True, True, True])
    err = tip_velocity_error_mps(rendered[late], truth, times, late)
    np.testing.assert_allclose(err[:, 0], [0.5, 3.0], rtol=0, atol=1e-12)
    gap = np.array([True, False, True, True])
    err = tip_velocity_error_mps(rendered[gap], truth, times, gap)
    np.testing.assert_allclose(err[:, 0], [3.0], rtol=0, atol=1e-12)
    none = tip_velocity_error_mps(rendered[:0], truth, times, np.zeros(4, dtype=bool))
    assert none.shape == (0, 1)
    with pytest.raises(ValueError, match="shape"):
        tip_velocity_error_mps(rendered, truth, times, late)


def _parabola() -> tuple[Trace, KeyframeLog]:
    """A left hand at x = t^2 sampled at 10 Hz, keyframes at 0, 0.2, 0.4 s (true velocities)."""
    times = np.arange(5) / 10.0
    poses = _poses(list(times**2), [IDENTITY] * 5)
    trace = Trace("parabola", times, poses, ("left",))
    idx = np.array([0, 2, 4])
    vel = np.zeros((3, 1, 6))
    vel[:, 0, 0] = 2.0 * times[idx]
    return trace, KeyframeLog(times[idx], times[idx], poses[idx], velocities=vel)


def test_evaluate_group_reports_the_velocity_error_per_class() -> None:
    """x = t^2 by SoA: rendered x = 0, .02, .04, .10, .16 against 0, .01, .04, .09, .16,
    so velocities .2, .2, .6, .6 against .1, .3, .5, .7 m/s: every error is 0.1 m/s.
    The Hermite methods get the true velocities, and a cubic reproduces t^2: no error."""
    trace, log = _parabola()
    methods = ["soa", "soa-hermite", "motor-hermite"]
    out = summarize([evaluate_group(trace, log, 0.3, methods)])
    soa = out["soa"]["hands"]
    assert soa["vel_p50_mps"] == pytest.approx(0.1, abs=1e-12)
    assert soa["vel_p95_mps"] == pytest.approx(0.1, abs=1e-12)
    assert soa["tip_p95_mm"] == pytest.approx(10.0, abs=1e-9)  # 0, 10, 0, 10, 0 mm
    for m in ("soa-hermite", "motor-hermite"):
        assert out[m]["hands"]["vel_p95_mps"] < 1e-12
        assert out[m]["hands"]["tip_p95_mm"] < 1e-9


def test_stat_keys_put_the_velocity_error_beside_the_tip_error() -> None:
    keys = list(STAT_KEYS)
    assert keys[keys.index("tip_p95_mm") + 1 :][:2] == ["vel_p50_mps", "vel_p95_mps"]
    assert list(ErrorSamples().stats()) == keys


def test_without_velocity_samples_the_other_statistics_are_unchanged() -> None:
    """The keys are added (NaN when not measured); the existing values do not move."""
    rng = np.random.default_rng(0)
    pos, rot, tip, vel = (rng.uniform(0, 5, 50) for _ in range(4))
    plain, measured = ErrorSamples(), ErrorSamples()
    plain.add(pos, rot, tip, 3, 50)
    measured.add(pos, rot, tip, 3, 50, vel=vel)
    a, b = plain.stats(), measured.stats()
    assert math.isnan(a["vel_p50_mps"]) and math.isnan(a["vel_p95_mps"])
    assert {k: v for k, v in a.items() if not k.startswith("vel_")} == {
        k: v for k, v in b.items() if not k.startswith("vel_")
    }
    merged = ErrorSamples()
    merged.merge(measured)
    assert merged.stats() == b


def test_compare_reports_velocity_error_for_every_method(dev_trace_path: Path) -> None:
    """The compare pipeline's per-class dicts carry finite vel_p50/p95 beside tip_p95."""
    trace = load_trace(dev_trace_path)
    methods = ["soa", "motor-lerp", "soa-hermite", "motor-hermite"]
    res = compare_trace(trace, [15.0], methods)
    for m in methods:
        for cls, st in res[15.0][m].items():
            assert set(st) == set(STAT_KEYS), (m, cls)
            assert 0.0 <= st["vel_p50_mps"] <= st["vel_p95_mps"] < math.inf
