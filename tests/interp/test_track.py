"""Keyframe tracks: ``interp.bracket`` and ``interp.evaluate_track``."""

from __future__ import annotations

import re

import numpy as np
import pytest
from numpy.typing import ArrayLike, NDArray

from posecast import interp

F64 = NDArray[np.float64]

METHODS = ("soa", "dq-slerp", "motor-lerp")


def random_poses(rng: np.random.Generator, shape: tuple[int, ...]) -> F64:
    """Poses of batch ``shape``: positions within 3 m per axis, unit quaternions."""
    q = rng.normal(size=(*shape, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return np.concatenate([rng.uniform(-3.0, 3.0, (*shape, 3)), q], axis=-1)


def keyframe_track(k: int = 6, streams: int = 4, seed: int = 0) -> tuple[F64, F64]:
    """Irregular, strictly increasing times ``(K,)`` and keyframes ``(K, S, 7)``."""
    rng = np.random.default_rng(seed)
    times = 10.0 + np.cumsum(rng.uniform(0.02, 0.2, k))
    return times, random_poses(rng, (k, streams))


# --- bracket --------------------------------------------------------------------


def test_bracket_matches_searchsorted_inside_the_track() -> None:
    """Inside the track: t[lo] <= q < t[hi], hi = lo + 1 from searchsorted, s is the fraction."""
    times, _ = keyframe_track(k=30)
    rng = np.random.default_rng(1)
    query = np.sort(rng.uniform(times[0], times[-1], 500))
    query = query[query < times[-1]]
    br = interp.bracket(times, query)
    expected_hi = np.searchsorted(times, query, side="right")
    np.testing.assert_array_equal(br.hi, expected_hi)
    np.testing.assert_array_equal(br.lo, expected_hi - 1)
    assert np.all(times[br.lo] <= query) and np.all(query < times[br.hi])
    s = (query - times[br.lo]) / (times[br.hi] - times[br.lo])
    np.testing.assert_allclose(br.s, s, rtol=0, atol=1e-15)
    assert not br.held.any()


def test_bracket_on_keyframe_times_gives_s_zero() -> None:
    """A query on keyframe k brackets (k, k+1) with s = 0; on the last, (K-1, K-1)."""
    times, _ = keyframe_track(k=5)
    br = interp.bracket(times, times)
    np.testing.assert_array_equal(br.lo, np.arange(5))
    np.testing.assert_array_equal(br.hi, [1, 2, 3, 4, 4])
    np.testing.assert_array_equal(br.s, np.zeros(5))
    assert not br.held.any()


def test_bracket_holds_outside_the_track() -> None:
    """Before the first keyframe: held on keyframe 0; after the last: held on K-1."""
    times = np.array([1.0, 2.0, 4.0])
    br = interp.bracket(times, [0.0, 0.999, 4.0 + 1e-12, 100.0])
    np.testing.assert_array_equal(br.lo, [0, 0, 2, 2])
    np.testing.assert_array_equal(br.hi, [0, 0, 2, 2])
    np.testing.assert_array_equal(br.s, np.zeros(4))
    np.testing.assert_array_equal(br.held, [True, True, True, True])


def test_bracket_with_a_single_keyframe() -> None:
    """K = 1: the keyframe's own time is not held; every other time is."""
    br = interp.bracket([3.0], [2.0, 3.0, 4.0])
    np.testing.assert_array_equal(br.lo, [0, 0, 0])
    np.testing.assert_array_equal(br.hi, [0, 0, 0])
    np.testing.assert_array_equal(br.s, np.zeros(3))
    np.testing.assert_array_equal(br.held, [True, False, True])


def test_bracket_accepts_an_empty_query() -> None:
    """Q = 0 gives empty brackets."""
    br = interp.bracket([0.0, 1.0], np.empty(0))
    assert br.lo.shape == br.hi.shape == br.s.shape == br.held.shape == (0,)


@pytest.mark.parametrize(
    ("times", "query", "message"),
    [
        ([], [0.0], "expected `times` to have shape (K,) with K >= 1, got (0,)"),
        ([[0.0, 1.0]], [0.0], "expected `times` to have shape (K,) with K >= 1, got (1, 2)"),
        ([0.0, 1.0], [[0.5]], "expected `query` to have shape (Q,), got (1, 1)"),
        ([0.0, 1.0], 0.5, "expected `query` to have shape (Q,), got ()"),
        ([0.0, np.nan], [0.5], "expected `times` and `query` to hold finite values"),
        ([0.0, 1.0], [np.inf], "expected `times` and `query` to hold finite values"),
        ([0.0, 2.0, 1.0], [0.5], "expected `times` to be strictly increasing"),
        ([0.0, 1.0, 1.0], [0.5], "expected `times` to be strictly increasing"),
    ],
)
def test_bracket_rejects_invalid_input(times: ArrayLike, query: ArrayLike, message: str) -> None:
    """Empty, multi-dimensional, non-finite or non-increasing inputs raise ValueError."""
    with pytest.raises(ValueError, match=re.escape(message)):
        interp.bracket(times, query)


# --- evaluate_track -----------------------------------------------------------


@pytest.mark.parametrize("method", METHODS)
def test_track_reproduces_keyframes_at_their_times(method: str) -> None:
    """Querying at the keyframe times returns the keyframes bit for bit, none held."""
    times, poses = keyframe_track()
    result = interp.evaluate_track(times, poses, times, method)
    np.testing.assert_array_equal(result.poses, poses)
    assert not result.held.any()


@pytest.mark.parametrize("method", METHODS)
def test_track_interpolates_every_stream_in_one_call(method: str) -> None:
    """All S streams at all Q queries equal the interpolator applied per bracket and stream."""
    times, poses = keyframe_track(k=8, streams=5)
    query = np.linspace(times[0], times[-1], 23)
    result = interp.evaluate_track(times, poses, query, method)
    assert result.poses.shape == (23, 5, 7)
    f = interp.get(method)
    for i, q in enumerate(query):
        k = min(int(np.searchsorted(times, q, side="right")) - 1, len(times) - 2)
        s = (q - times[k]) / (times[k + 1] - times[k])
        for stream in range(5):
            want = f(poses[k, stream], poses[k + 1, stream], s)
            np.testing.assert_allclose(result.poses[i, stream], want, rtol=0, atol=1e-14)


def test_track_calls_the_interpolator_once_for_all_streams() -> None:
    """evaluate_track makes one batched call with (Q, S, 7) keyframes and (Q, 1) fractions."""
    times, poses = keyframe_track(k=30, streams=100)
    shapes: list[tuple[tuple[int, ...], ...]] = []

    def spy(a: ArrayLike, b: ArrayLike, s: ArrayLike) -> F64:
        shapes.append((np.shape(a), np.shape(b), np.shape(s)))
        return interp.motor_lerp(a, b, s)

    query = np.array([times[3] + 0.01, times[17] + 0.005])
    result = interp.evaluate_track(times, poses, query, spy)
    assert shapes == [((2, 100, 7), (2, 100, 7), (2, 1))]
    np.testing.assert_array_equal(
        result.poses, interp.evaluate_track(times, poses, query, "motor-lerp").poses
    )


@pytest.mark.parametrize("method", METHODS)
def test_track_holds_and_reports_outside_the_keyframes(method: str) -> None:
    """Before the first / after the last keyframe the nearest one is shown and ``held`` set."""
    times, poses = keyframe_track()
    query = np.array([times[0] - 1.0, times[0] - 1e-9, times[-1] + 1e-9, times[-1] + 5.0])
    result = interp.evaluate_track(times, poses, query, method)
    np.testing.assert_array_equal(result.held, [True, True, True, True])
    np.testing.assert_array_equal(result.poses[:2], np.stack([poses[0], poses[0]]))
    np.testing.assert_array_equal(result.poses[2:], np.stack([poses[-1], poses[-1]]))


@pytest.mark.parametrize("method", METHODS)
def test_track_query_on_the_last_keyframe_is_not_held(method: str) -> None:
    """A query exactly at the last keyframe time shows that keyframe and is not held."""
    times, poses = keyframe_track()
    result = interp.evaluate_track(times, poses, [times[-1]], method)
    np.testing.assert_array_equal(result.held, [False])
    np.testing.assert_array_equal(result.poses[0], poses[-1])


@pytest.mark.parametrize("method", METHODS)
def test_track_with_a_single_keyframe(method: str) -> None:
    """K = 1 shows that keyframe everywhere, held except at its own time."""
    _, poses = keyframe_track(k=1, streams=3)
    result = interp.evaluate_track([5.0], poses, [4.0, 5.0, 6.0], method)
    np.testing.assert_array_equal(result.held, [True, False, True])
    np.testing.assert_array_equal(result.poses, np.broadcast_to(poses[0], (3, 3, 7)))


def test_track_of_one_stream_accepts_k_by_7() -> None:
    """Keyframes (K, 7) are one stream: the result is (Q, 1, 7)."""
    times, poses = keyframe_track(streams=1)
    query = np.linspace(times[0], times[-1], 9)
    flat = interp.evaluate_track(times, poses[:, 0, :], query, "dq-slerp")
    full = interp.evaluate_track(times, poses, query, "dq-slerp")
    assert flat.poses.shape == (9, 1, 7)
    np.testing.assert_array_equal(flat.poses, full.poses)
    np.testing.assert_array_equal(flat.held, full.held)


def test_track_defaults_to_soa_and_takes_an_empty_query() -> None:
    """The default method is SoA; an empty query gives (0, S, 7)."""
    times, poses = keyframe_track(streams=2)
    query = np.array([times[1] + 0.3 * (times[2] - times[1])])
    np.testing.assert_array_equal(
        interp.evaluate_track(times, poses, query).poses,
        interp.evaluate_track(times, poses, query, "soa").poses,
    )
    empty = interp.evaluate_track(times, poses, np.empty(0), "motor-lerp")
    assert empty.poses.shape == (0, 2, 7)
    assert empty.held.shape == (0,)


def test_track_does_not_modify_its_keyframes() -> None:
    """Off-unit keyframe quaternions are normalised in a copy, not in the caller's array."""
    times, poses = keyframe_track()
    poses[..., 3:] *= 2.0
    before = poses.copy()
    result = interp.evaluate_track(times, poses, times[:3] + 0.01, "soa")
    np.testing.assert_array_equal(poses, before)
    np.testing.assert_allclose(np.linalg.norm(result.poses[..., 3:], axis=-1), 1.0, atol=1e-15)


@pytest.mark.parametrize(
    ("times", "poses_shape", "query", "error", "message"),
    [
        ([0.0, 1.0], (2, 3, 6), [0.5], ValueError, "expected `poses` to have shape (..., 7)"),
        ([0.0, 1.0], (2, 3, 1, 7), [0.5], ValueError, "(K, S, 7), got (2, 3, 1, 7)"),
        ([0.0], (7,), [0.5], ValueError, "(K, S, 7), got (7,)"),
        ([0.0, 1.0, 2.0], (2, 3, 7), [0.5], ValueError, "`times` to have shape (2,), got (3,)"),
        ([1.0, 0.0], (2, 3, 7), [0.5], ValueError, "strictly increasing"),
        ([0.0, 1.0], (2, 3, 7), [np.nan], ValueError, "finite values"),
    ],
)
def test_track_rejects_invalid_input(
    times: ArrayLike,
    poses_shape: tuple[int, ...],
    query: ArrayLike,
    error: type[Exception],
    message: str,
) -> None:
    """Wrong shapes, unsorted times and non-finite queries raise ValueError with a reason."""
    poses = np.zeros(poses_shape)
    if poses_shape[-1] == 7:
        poses[..., 3] = 1.0
    with pytest.raises(error, match=re.escape(message)):
        interp.evaluate_track(times, poses, query, "soa")


def test_track_rejects_non_finite_keyframes_and_unknown_methods() -> None:
    """NaN keyframes raise ValueError; an unknown method name raises KeyError."""
    times, poses = keyframe_track()
    broken = poses.copy()
    broken[2, 1, 0] = np.nan
    with pytest.raises(ValueError, match="expected `poses` to hold finite values"):
        interp.evaluate_track(times, broken, [times[1]], "soa")
    with pytest.raises(KeyError, match="unknown interpolator 'nope'"):
        interp.evaluate_track(times, poses, [times[1]], "nope")
