"""scenarios.error_model: |a| dt^2 / 8 on motions whose answer is known."""

from __future__ import annotations

import numpy as np
import pytest

from posecast.scenarios.error_model import _intervals, causal_acceleration


def test_constant_acceleration_is_measured_and_predicted_alike() -> None:
    """A parabola (|a| = 4 m/s^2) sampled at 90 Hz: the estimate is 4 m/s^2 once the
    window has filled, and each interval's largest LERP error is a dt^2 / 8."""
    times = np.arange(0.0, 3.0, 1 / 90)
    pos = np.zeros((times.size, 3))
    pos[:, 1] = 0.5 * 4.0 * times**2
    acc = causal_acceleration(times, pos)
    assert acc[60:] == pytest.approx(4.0, rel=1e-6)
    measured, predicted = _intervals(times[60:], pos[60:], acc[60:], 10.0)
    assert measured.size > 10
    # The chord's largest gap is at mid-interval; native samples may miss it by a bit.
    assert np.all(measured <= predicted * (1 + 1e-9))
    assert np.all(measured >= 0.95 * predicted)


def test_the_estimate_is_causal() -> None:
    """A jolt at t = 1 s is not seen before it happens."""
    times = np.arange(0.0, 2.0, 1 / 60)
    pos = np.zeros((times.size, 3))
    pos[times >= 1.0, 0] = 0.01
    acc = causal_acceleration(times, pos)
    assert np.all(acc[times < 1.0] == 0.0) and acc.max() > 0.0
