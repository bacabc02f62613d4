"""The causal velocity estimator: past samples only, exact on the motions it claims."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from posecast.scenarios.traces import (
    CAUSAL_DEGREE,
    CAUSAL_SAMPLES,
    VELOCITY_SOURCES,
    Trace,
    causal_velocities,
    load_trace,
)
from posecast.scenarios.velocity_sources import compare_velocity_sources, source_velocities


def uneven_times(n: int, seed: int = 0) -> np.ndarray:
    """Sample times with jittered spacing around 90 Hz."""
    rng = np.random.default_rng(seed)
    return np.cumsum(rng.uniform(0.008, 0.014, n))


def spin_and_slide(times: np.ndarray, omega: np.ndarray, v: np.ndarray, acc: float = 0.0) -> Trace:
    """One stream: constant world angular velocity, position p0 + v t + acc t^2 / 2 on x."""
    rot = Rotation.from_rotvec(times[:, None] * omega[None, :]) * Rotation.from_euler(
        "xyz", [0.3, -0.2, 1.1]
    )
    quat = rot.as_quat()[:, [3, 0, 1, 2]]  # scipy is scalar-last
    pos = np.array([0.1, 1.2, -0.4]) + times[:, None] * v[None, :]
    pos[:, 0] += 0.5 * acc * times**2
    return Trace("fixture", times, np.concatenate([pos, quat], axis=1)[:, None, :], ("left",))


@pytest.mark.parametrize(("samples", "degree"), [(2, 1), (3, 1), (4, 2), (5, 3)])
def test_exact_for_constant_spin_and_constant_velocity(samples: int, degree: int) -> None:
    """World angular velocity and linear velocity are recovered exactly (to rounding)."""
    times = uneven_times(200)
    omega = np.array([2.0, -7.0, 4.5])
    v = np.array([0.7, -1.5, 2.5])
    vel = spin_and_slide(times, omega, v).causal_velocities(samples, degree)
    assert vel.shape == (200, 1, 6)
    assert np.all(vel[0] == 0.0)  # nothing in the past at the first sample
    np.testing.assert_allclose(vel[1:, 0, :3], np.broadcast_to(v, (199, 3)), atol=1e-9)
    np.testing.assert_allclose(vel[1:, 0, 3:], np.broadcast_to(omega, (199, 3)), atol=1e-7)


def test_quadratic_fit_is_exact_under_acceleration_and_backward_difference_is_not() -> None:
    times = uneven_times(100, seed=1)
    trace = spin_and_slide(times, np.zeros(3), np.array([1.0, 0.0, 0.0]), acc=20.0)
    true_vx = 1.0 + 20.0 * times
    quad = trace.causal_velocities(4, 2)
    np.testing.assert_allclose(quad[3:, 0, 0], true_vx[3:], atol=1e-8)
    back = trace.causal_velocities(2, 1)
    # Backward difference: the slope of the last chord, lagging by half an interval.
    want = 1.0 + 20.0 * 0.5 * (times[1:] + times[:-1])
    np.testing.assert_allclose(back[1:, 0, 0], want, atol=1e-9)
    assert np.all(np.abs(back[3:, 0, 0] - true_vx[3:]) > 0.05)


def test_only_the_past_is_used() -> None:
    """Changing samples after n never changes the velocity reported at n."""
    rng = np.random.default_rng(2)
    times = uneven_times(60, seed=2)
    trace = spin_and_slide(times, np.array([1.0, 3.0, -2.0]), np.array([0.2, 0.1, 0.0]))
    base = trace.causal_velocities()
    for n in (0, 1, 2, 5, 30, 58):
        poses = trace.poses.copy()
        poses[n + 1 :, :, :3] += rng.normal(size=poses[n + 1 :, :, :3].shape)
        q = rng.normal(size=poses[n + 1 :, :, 3:].shape)
        poses[n + 1 :, :, 3:] = q / np.linalg.norm(q, axis=-1, keepdims=True)
        changed = Trace("x", times, poses, trace.streams).causal_velocities()
        np.testing.assert_array_equal(changed[: n + 1], base[: n + 1])
        assert not np.array_equal(changed[n + 1 :], base[n + 1 :])


def test_sign_of_quaternions_does_not_matter() -> None:
    times = uneven_times(50, seed=3)
    trace = spin_and_slide(times, np.array([0.0, 9.0, 1.0]), np.zeros(3))
    flipped = trace.poses.copy()
    flipped[1::2, :, 3:] *= -1.0
    np.testing.assert_allclose(
        Trace("x", times, flipped, trace.streams).causal_velocities(),
        trace.causal_velocities(),
        atol=1e-9,
    )


def test_sources_and_defaults() -> None:
    times = uneven_times(30, seed=4)
    trace = spin_and_slide(times, np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    assert VELOCITY_SOURCES == ("central", "causal")
    np.testing.assert_array_equal(trace.velocities_from("central"), trace.velocities())
    np.testing.assert_array_equal(
        trace.velocities_from("causal"),
        causal_velocities(times, trace.poses, CAUSAL_SAMPLES, CAUSAL_DEGREE),
    )
    with pytest.raises(ValueError, match="unknown velocity source"):
        trace.velocities_from("future")
    for samples, degree in ((1, 1), (3, 0), (3, 3)):
        with pytest.raises(ValueError, match="samples"):
            trace.causal_velocities(samples, degree)


def test_compare_velocity_sources_scores_each_source(dev_trace_path: Path) -> None:
    """The source comparison rounds to float16 and scores hands at each rate per source."""
    trace = load_trace(dev_trace_path).window(10.0, 25.0)
    vel = source_velocities(trace, "causal:2,1")
    np.testing.assert_array_equal(
        vel, trace.causal_velocities(2, 1).astype(np.float16).astype(np.float64)
    )
    res = compare_velocity_sources([trace], [10.0, 20.0], ["central", "causal", "causal:2,1"])
    assert set(res) == {"central", "causal", "causal:2,1"}
    for per_rate in res.values():
        assert set(per_rate) == {10.0, 20.0}
        for st in per_rate.values():
            assert 0 < st["tip_p50_mm"] <= st["tip_p95_mm"] < 1e4
    # Different velocities give different errors (the source is really used).
    assert res["central"][20.0] != res["causal:2,1"][20.0]
    with pytest.raises(ValueError, match="malformed source"):
        source_velocities(trace, "causal:x")
