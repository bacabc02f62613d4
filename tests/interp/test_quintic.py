"""Properties of motor-quintic (C2 quintic on motors over 6 keyframes), with hypothesis.

Windows are random walks of rigid motions at non-uniform times (neighbours well
under a half turn apart, as consecutive keyframes of a tracked device are). A
change of *world* frame is ``G a``, a change of *body* frame ``a H``.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray

from posecast import interp
from posecast.interp.extrapolate import twist_extrapolate
from posecast.interp.quintic import motor_window_spline

F64 = NDArray[np.float64]

PROPERTY_SETTINGS = settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)

seeds = st.integers(0, 2**32 - 1)
fraction = st.floats(0.0, 1.0, allow_nan=False)

LB = LA = 2
K = LB + 2 + LA


def _unit(v: F64) -> F64:
    out: F64 = v / np.linalg.norm(v, axis=-1, keepdims=True)
    return out


def random_pose(rng: np.random.Generator) -> F64:
    return np.concatenate([rng.uniform(-2.0, 2.0, 3), _unit(rng.normal(size=4))])


def walk(rng: np.random.Generator, n: int) -> tuple[F64, F64]:
    """``n`` keyframes at increasing non-uniform times, each a random screw from the last."""
    times = np.cumsum(rng.uniform(0.03, 0.2, n))
    keys = [random_pose(rng)]
    for k in range(1, n):
        vel = np.concatenate([rng.uniform(-3, 3, 3), rng.uniform(-10, 10, 3)])
        keys.append(twist_extrapolate(keys[-1], vel, times[k] - times[k - 1]))
    return np.stack(keys), times


def compose(g: F64, a: F64) -> F64:
    """Rigid product ``g a`` (broadcasting)."""
    g, a = np.broadcast_arrays(g, a)
    t = g[..., :3] + interp.quat_rotate(g[..., 3:], a[..., :3])
    return np.concatenate([t, interp.quat_mul(g[..., 3:], a[..., 3:])], axis=-1)


def angle(q0: F64, q1: F64) -> F64:
    q1 = q1 * np.where(np.sum(q0 * q1, axis=-1) < 0.0, -1.0, 1.0)[..., None]
    out: F64 = 4.0 * np.arctan2(np.linalg.norm(q1 - q0, axis=-1), np.linalg.norm(q1 + q0, axis=-1))
    return out


def assert_same_poses(got: F64, want: F64, tol: float = 1e-11) -> None:
    dp = float(np.max(np.linalg.norm(got[..., :3] - want[..., :3], axis=-1)))
    dq = float(np.max(angle(got[..., 3:], want[..., 3:])))
    assert dp <= tol, f"positions differ by {dp:.3g} m"
    assert dq <= tol, f"rotations differ by {dq:.3g} rad"


def at(keys: F64, times: F64, u: float) -> F64:
    """motor-quintic on a 6-keyframe window at fraction ``u`` of its bracket."""
    t = times[LB] + u * (times[LB + 1] - times[LB])
    return interp.get("motor-quintic")(keys, times, t)


def test_motor_quintic_is_registered_with_its_window() -> None:
    """Registered as a frame-invariant window method: 2 keyframes each side, 6 in all."""
    entry = interp.info("motor-quintic")
    assert (entry.kind, entry.lookbehind, entry.lookahead) == ("window", 2, 2)
    assert entry.window_size == 6 and entry.frame_invariant and not entry.needs_velocity


@PROPERTY_SETTINGS
@given(seed=seeds)
def test_quintic_endpoints_are_the_bracket_keyframes(seed: int) -> None:
    """At the bracket's times motor-quintic returns its keyframes bit for bit."""
    keys, times = walk(np.random.default_rng(seed), K)
    np.testing.assert_array_equal(at(keys, times, 0.0), keys[LB])
    np.testing.assert_array_equal(at(keys, times, 1.0), keys[LB + 1])


@PROPERTY_SETTINGS
@given(seed=seeds, u=fraction, which=st.integers(0, K - 1))
def test_quintic_is_blind_to_quaternion_signs(seed: int, u: float, which: int) -> None:
    """Negating any window keyframe's quaternion leaves the curve unchanged."""
    keys, times = walk(np.random.default_rng(seed), K)
    flipped = keys.copy()
    flipped[which, 3:] *= -1.0
    assert_same_poses(at(flipped, times, u), at(keys, times, u))


@PROPERTY_SETTINGS
@given(seed=seeds, u=fraction)
def test_quintic_outputs_unit_quaternions(seed: int, u: float) -> None:
    """The output quaternion has unit norm to 1e-14."""
    keys, times = walk(np.random.default_rng(seed), K)
    assert abs(float(np.linalg.norm(at(keys, times, u)[3:])) - 1.0) <= 1e-14


@PROPERTY_SETTINGS
@given(seed=seeds, u=fraction)
def test_quintic_commutes_with_world_and_body_frame_changes(seed: int, u: float) -> None:
    """quintic(G K H) = G quintic(K) H for rigid G (world) and H (body)."""
    rng = np.random.default_rng(seed)
    keys, times = walk(rng, K)
    g, h = random_pose(rng), random_pose(rng)
    want = compose(compose(g, at(keys, times, u)), h)
    got = at(compose(compose(g, keys), h), times, u)
    assert_same_poses(got, want, 1e-10)


@PROPERTY_SETTINGS
@given(seed=seeds, u=fraction)
def test_quintic_reproduces_quartic_translation(seed: int, u: float) -> None:
    """A translation along a quartic in time at a fixed orientation is exact (non-uniform times)."""
    rng = np.random.default_rng(seed)
    times = np.cumsum(rng.uniform(0.03, 0.2, K))
    coef = rng.uniform(-3.0, 3.0, (5, 3))
    q = _unit(rng.normal(size=4))

    def pose(t: float) -> F64:
        return np.concatenate([sum(coef[i] * t**i for i in range(5)), q])

    keys = np.stack([pose(t) for t in times])
    t = times[LB] + u * (times[LB + 1] - times[LB])
    assert_same_poses(at(keys, times, u), pose(t), 1e-11)


@PROPERTY_SETTINGS
@given(seed=seeds)
def test_quintic_is_c2_across_a_keyframe(seed: int) -> None:
    """Neighbouring windows meet at a shared keyframe with equal pose, velocity, acceleration."""
    keys, times = walk(np.random.default_rng(seed), K + 1)
    f = interp.get("motor-quintic")

    def left(t: float) -> F64:
        return f(keys[0:K], times[0:K], t)

    def right(t: float) -> F64:
        return f(keys[1 : K + 1], times[1 : K + 1], t)

    tk = float(times[LB + 1])  # hi of the left window, lo of the right one
    np.testing.assert_array_equal(left(tk), right(tk))
    ref = left(tk)[3:]

    def flat(p: F64) -> F64:
        q = p[3:] * (1.0 if float(np.dot(p[3:], ref)) >= 0 else -1.0)
        return np.concatenate([p[:3], q])

    def one_sided(h: float) -> tuple[list[F64], list[F64]]:
        return [flat(left(tk - i * h)) for i in range(4)], [
            flat(right(tk + i * h)) for i in range(4)
        ]

    # Second-order one-sided first derivatives (small step: little truncation) ...
    h = 1e-6
    lft, rgt = one_sided(h)
    v_left = (3 * lft[0] - 4 * lft[1] + lft[2]) / (2 * h)
    v_right = -(3 * rgt[0] - 4 * rgt[1] + rgt[2]) / (2 * h)
    scale_v = max(1.0, float(np.max(np.abs(v_left))))
    np.testing.assert_allclose(v_left, v_right, rtol=0, atol=1e-6 * scale_v)

    # ... and second derivatives (larger steps: rounding grows as 1/h^2), with one
    # Richardson step to cancel the h^2 truncation term.
    def second(h: float) -> tuple[F64, F64]:
        lft, rgt = one_sided(h)
        a_left = (2 * lft[0] - 5 * lft[1] + 4 * lft[2] - lft[3]) / h**2
        a_right = (2 * rgt[0] - 5 * rgt[1] + 4 * rgt[2] - rgt[3]) / h**2
        return a_left, a_right

    (l1, r1), (l2, r2) = second(2e-4), second(1e-4)
    a_left, a_right = (4 * l2 - l1) / 3, (4 * r2 - r1) / 3
    scale_a = max(1.0, float(np.max(np.abs(a_left))))
    np.testing.assert_allclose(a_left, a_right, rtol=0, atol=1e-3 * scale_a)


def test_quintic_velocity_jumps_without_a_shared_stencil() -> None:
    """The C2 test can fail: two windows that disagree at the keyframe give a velocity jump."""
    keys, times = walk(np.random.default_rng(3), K + 1)
    f = interp.get("motor-quintic")
    other = keys.copy()
    other[K - 1, :3] += 0.05  # in both stencils at the shared keyframe: the right one moves
    tk, h = float(times[LB + 1]), 1e-5
    v_left = (f(keys[0:K], times[0:K], tk) - f(keys[0:K], times[0:K], tk - h)) / h
    v_right = (f(other[1:], times[1:], tk + h) - f(other[1:], times[1:], tk)) / h
    assert float(np.max(np.abs(v_left[:3] - v_right[:3]))) > 1e-3


def test_quintic_with_only_the_bracket_is_motor_lerp() -> None:
    """With every neighbour missing (repeats of the bracket) the curve is the motor blend."""
    keys, times = walk(np.random.default_rng(11), 2)
    window = keys[[0, 0, 0, 1, 1, 1]]
    wt = times[[0, 0, 0, 1, 1, 1]]
    for s in (0.1, 0.5, 0.9):
        t = times[0] + s * (times[1] - times[0])
        assert_same_poses(
            interp.motor_quintic(window, wt, t), interp.motor_lerp(keys[0], keys[1], s), 1e-13
        )


@pytest.mark.parametrize("missing", ["start", "end", "both"])
def test_quintic_at_track_ends_uses_the_keyframes_that_exist(missing: str) -> None:
    """A missing neighbour is the lower-degree fit: a cubic translation stays exact near ends."""
    times = np.array([0.0, 0.07, 0.2, 0.31, 0.45, 0.52])
    coef = np.array([[0.1, -0.2, 0.3], [1.0, 0.5, -2.0], [-3.0, 2.0, 1.0], [4.0, -1.0, 2.0]])
    q = _unit(np.array([0.3, -0.1, 0.8, 0.2]))
    keys = np.stack([np.concatenate([sum(coef[i] * t**i for i in range(4)), q]) for t in times])
    idx = {"start": [1, 1, 2, 3, 4, 5], "end": [0, 1, 2, 3, 4, 4], "both": [1, 1, 2, 3, 4, 4]}
    sel = idx[missing]
    for s in (0.2, 0.6):
        t = times[2] + s * (times[3] - times[2])
        want = np.concatenate([sum(coef[i] * t**i for i in range(4)), q])
        assert_same_poses(interp.motor_quintic(keys[sel], times[sel], t), want, 1e-12)


def test_quintic_held_bracket_returns_its_keyframe() -> None:
    """A held query (lo == hi, same time; neighbours after repeat it) shows lo exactly."""
    keys, times = walk(np.random.default_rng(5), 3)
    window = keys[[0, 1, 2, 2, 2, 2]]
    wt = times[[0, 1, 2, 2, 2, 2]]
    np.testing.assert_array_equal(interp.motor_quintic(window, wt, times[2] + 0.05), keys[2])


def test_quintic_batches_and_broadcasts() -> None:
    """A (Q, S, 6, 7) window batch equals the per-window results; times and t broadcast."""
    rng = np.random.default_rng(2)
    wins = [walk(rng, K) for _ in range(6)]
    keys = np.stack([w[0] for w in wins]).reshape(3, 2, K, 7)
    times = np.stack([w[1] for w in wins]).reshape(3, 2, K)
    t = times[..., LB] + 0.3 * (times[..., LB + 1] - times[..., LB])
    out = interp.motor_quintic(keys, times, t)
    assert out.shape == (3, 2, 7)
    for i in range(3):
        for j in range(2):
            want = interp.motor_quintic(keys[i, j], times[i, j], t[i, j])
            np.testing.assert_array_equal(out[i, j], want)
    shared = interp.motor_quintic(keys, times[0, 0], times[0, 0, LB] + 0.01)
    assert shared.shape == (3, 2, 7)


def test_window_spline_other_sizes_keep_the_properties() -> None:
    """The same construction with 1 or 3 neighbours per side still passes through its keyframes."""
    keys, times = walk(np.random.default_rng(9), 8)
    for lb, la in ((1, 1), (3, 3), (2, 0), (0, 2)):
        k = lb + 2 + la
        w, wt = keys[:k], times[:k]
        np.testing.assert_array_equal(motor_window_spline(w, wt, wt[lb], lb, la), w[lb])
        np.testing.assert_array_equal(motor_window_spline(w, wt, wt[lb + 1], lb, la), w[lb + 1])


@pytest.mark.parametrize(
    ("keys", "times", "t", "message"),
    [
        (np.zeros((4, 7)), np.zeros(4), 0.0, "expected `keys` to have shape (..., 6, 7)"),
        (np.zeros((6, 6)), np.zeros(6), 0.0, "expected `keys` to have shape (..., 6, 7)"),
        (None, np.zeros(5), 0.0, "expected `times` to have shape (..., 6)"),
        (None, np.array([0.0, 1, 2, 1, 4, 5]), 1.5, "expected non-decreasing window `times`"),
        (None, np.array([0.0, 1, 2, 3, 4, np.nan]), 2.5, "expected `times` to hold finite"),
        (None, np.arange(6.0), np.inf, "expected `t` to hold finite values"),
        (None, np.arange(6.0), np.zeros(3), "expected `t` broadcastable"),
        (None, np.zeros((2, 6)), 0.0, "expected `times` of shape (6,) to match `keys`"),
    ],
)
def test_quintic_rejects_bad_input(keys: F64 | None, times: F64, t: object, message: str) -> None:
    """Wrong window sizes, shapes, decreasing or non-finite times raise a clear ValueError."""
    if keys is None:
        keys = walk(np.random.default_rng(0), K)[0]
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        interp.motor_quintic(keys, times, t)  # type: ignore[arg-type]


def test_quintic_rejects_zero_quaternions() -> None:
    """A zero quaternion is not a rotation."""
    keys, times = walk(np.random.default_rng(0), K)
    keys[0, 3:] = 0.0
    with pytest.raises(ValueError, match="non-zero quaternions"):
        interp.motor_quintic(keys, times, times[LB] + 0.01)
