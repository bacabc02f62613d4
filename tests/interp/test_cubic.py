"""Properties of motor-cubic, motor-hermite and dead reckoning, checked with hypothesis.

Keyframe windows are random walks of rigid motions (neighbours less than
~115 degrees apart, as consecutive keyframes of a tracked device are), at
non-uniform times. A change of *world* frame is ``G a`` (velocities rotate
with ``G``); a change of *body* frame is ``a H`` (the angular velocity stays,
the origin's linear velocity becomes that of the new body point).
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray

from posecast import interp
from posecast.interp.extrapolate import twist_extrapolate

F64 = NDArray[np.float64]

PROPERTY_SETTINGS = settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)

seeds = st.integers(0, 2**32 - 1)
fraction = st.floats(0.0, 1.0, allow_nan=False)
interior = st.floats(0.05, 0.95, allow_nan=False)


# --- helpers ----------------------------------------------------------------------


def _unit(v: F64) -> F64:
    out: F64 = v / np.linalg.norm(v, axis=-1, keepdims=True)
    return out


def random_pose(rng: np.random.Generator) -> F64:
    return np.concatenate([rng.uniform(-2.0, 2.0, 3), _unit(rng.normal(size=4))])


def random_velocity(rng: np.random.Generator, lin: float = 3.0, ang: float = 6.0) -> F64:
    return np.concatenate([rng.uniform(-lin, lin, 3), rng.uniform(-ang, ang, 3)])


def walk(rng: np.random.Generator, n: int) -> tuple[F64, F64]:
    """``n`` keyframes at increasing non-uniform times, each a random motion from the last."""
    times = np.cumsum(rng.uniform(0.03, 0.2, n))
    keys = [random_pose(rng)]
    for k in range(1, n):
        dt = times[k] - times[k - 1]
        vel = random_velocity(rng, 3.0, 10.0)
        keys.append(twist_extrapolate(keys[-1], vel, dt))
    return np.stack(keys), times


def velocities_of(rng: np.random.Generator, n: int) -> F64:
    return np.stack([random_velocity(rng) for _ in range(n)])


def compose(g: F64, a: F64) -> F64:
    """Rigid product ``g a``: ``(t_g + R_g t_a, q_g q_a)``."""
    t = g[..., :3] + interp.quat_rotate(g[..., 3:], a[..., :3])
    return np.concatenate([t, interp.quat_mul(g[..., 3:], a[..., 3:])], axis=-1)


def rotate(q: F64, v: F64) -> F64:
    return interp.quat_rotate(np.broadcast_to(q, (*v.shape[:-1], 4)), v)


def world_velocity(g: F64, vel: F64) -> F64:
    """Velocities after the world change ``G``: both vectors rotate with it."""
    return np.concatenate([rotate(g[3:], vel[..., :3]), rotate(g[3:], vel[..., 3:])], axis=-1)


def body_velocity(pose: F64, h: F64, vel: F64) -> F64:
    """Velocities of the body point ``h`` of ``pose``: v + w x (R t_h), same w."""
    arm = interp.quat_rotate(pose[..., 3:], np.broadcast_to(h[:3], (*pose.shape[:-1], 3)))
    return np.concatenate([vel[..., :3] + np.cross(vel[..., 3:], arm), vel[..., 3:]], axis=-1)


def angle(q0: F64, q1: F64) -> F64:
    q1 = q1 * np.where(np.sum(q0 * q1, axis=-1) < 0.0, -1.0, 1.0)[..., None]
    out: F64 = 4.0 * np.arctan2(np.linalg.norm(q1 - q0, axis=-1), np.linalg.norm(q1 + q0, axis=-1))
    return out


def assert_same_poses(got: F64, want: F64, tol: float = 1e-11) -> None:
    dp = float(np.max(np.linalg.norm(got[..., :3] - want[..., :3], axis=-1)))
    dq = float(np.max(angle(got[..., 3:], want[..., 3:])))
    assert dp <= tol, f"positions differ by {dp:.3g} m"
    assert dq <= tol, f"rotations differ by {dq:.3g} rad"


def cubic_at(keys: F64, times: F64, t: float) -> F64:
    return interp.motor_cubic(keys, times, t)


def hermite_at(keys: F64, vel: F64, times: F64, k: int, t: float) -> F64:
    dt = times[k + 1] - times[k]
    return interp.motor_hermite(keys[k], keys[k + 1], vel[k], vel[k + 1], dt, (t - times[k]) / dt)


def aligned(q: F64, ref: F64) -> F64:
    out: F64 = q * (1.0 if float(np.dot(q, ref)) >= 0 else -1.0)
    return out


def one_sided_derivatives(f_left: object, f_right: object, t: float, h: float) -> tuple[F64, F64]:
    """Second-order one-sided derivatives of a pose curve (position, aligned quaternion)."""
    assert callable(f_left) and callable(f_right)
    p0 = f_left(t)
    ref = p0[3:]

    def flat(p: F64) -> F64:
        return np.concatenate([p[:3], aligned(p[3:], ref)])

    left = (3 * flat(f_left(t)) - 4 * flat(f_left(t - h)) + flat(f_left(t - 2 * h))) / (2 * h)
    right = (-3 * flat(f_right(t)) + 4 * flat(f_right(t + h)) - flat(f_right(t + 2 * h))) / (2 * h)
    return left, right


# --- motor-cubic ---------------------------------------------------------------------


@PROPERTY_SETTINGS
@given(seed=seeds)
def test_cubic_endpoints_are_the_bracket_keyframes(seed: int) -> None:
    """At T1 and T2 motor-cubic returns the bracket keyframes bit for bit."""
    keys, times = walk(np.random.default_rng(seed), 4)
    np.testing.assert_array_equal(cubic_at(keys, times, times[1]), keys[1])
    np.testing.assert_array_equal(cubic_at(keys, times, times[2]), keys[2])


@PROPERTY_SETTINGS
@given(seed=seeds, u=fraction, which=st.integers(0, 3))
def test_cubic_is_blind_to_quaternion_signs(seed: int, u: float, which: int) -> None:
    """Negating any window keyframe's quaternion leaves the curve unchanged."""
    keys, times = walk(np.random.default_rng(seed), 4)
    t = times[1] + u * (times[2] - times[1])
    flipped = keys.copy()
    flipped[which, 3:] *= -1.0
    assert_same_poses(cubic_at(flipped, times, t), cubic_at(keys, times, t))


@PROPERTY_SETTINGS
@given(seed=seeds, u=fraction)
def test_cubic_outputs_unit_quaternions(seed: int, u: float) -> None:
    """The output quaternion has unit norm to 1e-14."""
    keys, times = walk(np.random.default_rng(seed), 4)
    out = cubic_at(keys, times, times[1] + u * (times[2] - times[1]))
    assert abs(float(np.linalg.norm(out[3:])) - 1.0) <= 1e-14


@PROPERTY_SETTINGS
@given(seed=seeds, u=fraction)
def test_cubic_commutes_with_world_and_body_frame_changes(seed: int, u: float) -> None:
    """cubic(G K H) = G cubic(K) H for rigid G (world) and H (body)."""
    rng = np.random.default_rng(seed)
    keys, times = walk(rng, 4)
    g, h = random_pose(rng), random_pose(rng)
    t = times[1] + u * (times[2] - times[1])
    want = compose(compose(g, cubic_at(keys, times, t)), h)
    got = cubic_at(compose(compose(g, keys), h), times, t)
    assert_same_poses(got, want, 1e-10)


@PROPERTY_SETTINGS
@given(seed=seeds)
def test_cubic_is_c1_across_a_keyframe(seed: int) -> None:
    """Two neighbouring windows meet at their shared keyframe with equal pose and velocity."""
    keys, times = walk(np.random.default_rng(seed), 5)

    def left(t: float) -> F64:
        return cubic_at(keys[0:4], times[0:4], t)

    def right(t: float) -> F64:
        return cubic_at(keys[1:5], times[1:5], t)

    t2 = float(times[2])
    np.testing.assert_array_equal(left(t2), right(t2))
    d_left, d_right = one_sided_derivatives(left, right, t2, 1e-5)
    scale = max(1.0, float(np.max(np.abs(d_left))))
    np.testing.assert_allclose(d_left, d_right, rtol=0, atol=2e-5 * scale)


@PROPERTY_SETTINGS
@given(seed=seeds, u=fraction)
def test_cubic_reproduces_linear_motion(seed: int, u: float) -> None:
    """Constant-velocity translation at a fixed orientation is exact, at non-uniform times."""
    rng = np.random.default_rng(seed)
    times = np.cumsum(rng.uniform(0.03, 0.2, 4))
    p0, v, q = rng.uniform(-2, 2, 3), rng.uniform(-5, 5, 3), _unit(rng.normal(size=4))
    keys = np.stack([np.concatenate([p0 + v * t, q]) for t in times])
    t = times[1] + u * (times[2] - times[1])
    assert_same_poses(cubic_at(keys, times, t), np.concatenate([p0 + v * t, q]), 1e-12)


def test_cubic_missing_neighbours_fall_back_to_the_chord() -> None:
    """A window whose neighbours repeat the bracket keyframes stays between them."""
    keys, times = walk(np.random.default_rng(7), 4)
    window = np.stack([keys[1], keys[1], keys[2], keys[2]])
    wt = np.array([times[1], times[1], times[2], times[2]])
    out = interp.motor_cubic(window, wt, 0.5 * (times[1] + times[2]))
    assert np.all(np.isfinite(out)) and abs(float(np.linalg.norm(out[3:])) - 1.0) < 1e-14


# --- motor-hermite -------------------------------------------------------------------


@PROPERTY_SETTINGS
@given(seed=seeds)
def test_hermite_endpoints_are_the_keyframes(seed: int) -> None:
    """At s = 0 and s = 1 motor-hermite returns the keyframes bit for bit."""
    rng = np.random.default_rng(seed)
    keys, times = walk(rng, 2)
    vel = velocities_of(rng, 2)
    dt = times[1] - times[0]
    np.testing.assert_array_equal(
        interp.motor_hermite(keys[0], keys[1], vel[0], vel[1], dt, 0.0), keys[0]
    )
    np.testing.assert_array_equal(
        interp.motor_hermite(keys[0], keys[1], vel[0], vel[1], dt, 1.0), keys[1]
    )


@PROPERTY_SETTINGS
@given(seed=seeds, s=fraction, which=st.integers(0, 1))
def test_hermite_is_blind_to_quaternion_signs(seed: int, s: float, which: int) -> None:
    """Negating either keyframe's quaternion leaves the curve unchanged."""
    rng = np.random.default_rng(seed)
    keys, times = walk(rng, 2)
    vel = velocities_of(rng, 2)
    dt = times[1] - times[0]
    flipped = keys.copy()
    flipped[which, 3:] *= -1.0
    want = interp.motor_hermite(keys[0], keys[1], vel[0], vel[1], dt, s)
    got = interp.motor_hermite(flipped[0], flipped[1], vel[0], vel[1], dt, s)
    assert_same_poses(got, want)
    assert abs(float(np.linalg.norm(got[3:])) - 1.0) <= 1e-14


@PROPERTY_SETTINGS
@given(seed=seeds, s=fraction)
def test_hermite_commutes_with_world_and_body_frame_changes(seed: int, s: float) -> None:
    """hermite(G K H, velocities moved alike) = G hermite(K) H."""
    rng = np.random.default_rng(seed)
    keys, times = walk(rng, 2)
    vel = velocities_of(rng, 2)
    g, h = random_pose(rng), random_pose(rng)
    dt = times[1] - times[0]
    want = compose(compose(g, interp.motor_hermite(keys[0], keys[1], vel[0], vel[1], dt, s)), h)
    gk = compose(g, keys)
    gv = world_velocity(g, vel)
    moved = compose(gk, h)
    mv = body_velocity(gk, h, gv)
    got = interp.motor_hermite(moved[0], moved[1], mv[0], mv[1], dt, s)
    assert_same_poses(got, want, 1e-10)


@PROPERTY_SETTINGS
@given(seed=seeds)
def test_hermite_is_c1_across_a_keyframe(seed: int) -> None:
    """Segments sharing a keyframe and its velocity meet with equal pose and velocity."""
    rng = np.random.default_rng(seed)
    keys, times = walk(rng, 3)
    vel = velocities_of(rng, 3)

    def left(t: float) -> F64:
        return hermite_at(keys, vel, times, 0, t)

    def right(t: float) -> F64:
        return hermite_at(keys, vel, times, 1, t)

    t1 = float(times[1])
    np.testing.assert_array_equal(left(t1), right(t1))
    d_left, d_right = one_sided_derivatives(left, right, t1, 1e-5)
    scale = max(1.0, float(np.max(np.abs(d_left))))
    np.testing.assert_allclose(d_left, d_right, rtol=0, atol=2e-5 * scale)
    # ... and that velocity is the one given: dp/dt = v.
    np.testing.assert_allclose(d_right[:3], vel[1, :3], rtol=0, atol=2e-5 * scale)


@PROPERTY_SETTINGS
@given(seed=seeds, s=fraction)
def test_hermite_reproduces_linear_motion(seed: int, s: float) -> None:
    """Constant-velocity translation with its true velocity is exact."""
    rng = np.random.default_rng(seed)
    p0, v, q = rng.uniform(-2, 2, 3), rng.uniform(-5, 5, 3), _unit(rng.normal(size=4))
    dt = float(rng.uniform(0.03, 0.2))
    a, b = np.concatenate([p0, q]), np.concatenate([p0 + v * dt, q])
    vel = np.concatenate([v, np.zeros(3)])
    got = interp.motor_hermite(a, b, vel, vel, dt, s)
    assert_same_poses(got, np.concatenate([p0 + v * s * dt, q]), 1e-12)


def _screw_case(rng: np.random.Generator, step: float) -> tuple[F64, F64, F64, F64, float]:
    """A constant screw over one interval ``dt`` with ``|w| dt`` and ``|v| dt`` near ``step``."""
    a = random_pose(rng)
    vel = np.concatenate([_unit(rng.normal(size=3)), _unit(rng.normal(size=3))])
    dt = step
    b = twist_extrapolate(a, vel, dt)
    w = vel[3:]
    vb = np.concatenate([vel[:3] + np.cross(w, b[:3] - a[:3]), w])
    return a, b, vel, vb, dt


@PROPERTY_SETTINGS
@given(seed=seeds, s=fraction)
def test_hermite_follows_a_constant_screw_with_its_true_velocities(seed: int, s: float) -> None:
    """At 0.05 rad and 0.05 m per interval the screw is reproduced to 1e-9 m and rad."""
    a, b, va, vb, dt = _screw_case(np.random.default_rng(seed), 0.05)
    got = interp.motor_hermite(a, b, va, vb, dt, s)
    assert_same_poses(got, twist_extrapolate(a, va, s * dt), 1e-9)


def test_hermite_screw_error_is_fifth_order_not_zero() -> None:
    """A cubic in motor coefficients cannot trace a screw exactly: the error falls as dt^5."""
    errs = []
    s = np.linspace(0.0, 1.0, 41)
    for step in (0.4, 0.2, 0.1):
        a, b, va, vb, dt = _screw_case(np.random.default_rng(11), step)
        n = (s.size, 7)
        got = interp.motor_hermite(np.broadcast_to(a, n), np.broadcast_to(b, n), va, vb, dt, s)
        want = twist_extrapolate(a, va, s * dt)
        errs.append(float(np.max(np.linalg.norm(got[:, :3] - want[:, :3], axis=-1))))
    assert errs[0] > 1e-7  # visibly inexact at large steps ...
    orders = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    assert np.all(orders > 4.5), orders  # ... and fifth order as the step shrinks


# --- dead reckoning ------------------------------------------------------------------


@PROPERTY_SETTINGS
@given(seed=seeds, s=st.floats(0.0, 2.5, allow_nan=False))
def test_twist_extrapolation_is_screw_extrapolation(seed: int, s: float) -> None:
    """Constant-twist dead reckoning equals ScLERP continued along the same screw."""
    rng = np.random.default_rng(seed)
    a = random_pose(rng)
    # |w| < pi over the 1 s keyframe interval: past a half turn ScLERP rightly takes
    # the shorter way round, which is not this twist any more.
    vel = random_velocity(rng, 3.0, 1.7)
    b = twist_extrapolate(a, vel, 1.0)
    got = interp.screw_extrapolate(a, b, s, max_s=3.0)
    assert_same_poses(got, twist_extrapolate(a, vel, s), 1e-10)


@PROPERTY_SETTINGS
@given(seed=seeds, dt=st.floats(0.0, 0.3, allow_nan=False))
def test_twist_extrapolation_commutes_with_frame_changes(seed: int, dt: float) -> None:
    """Dead reckoning G a H with the moved velocity equals G (dead reckoning a) H."""
    rng = np.random.default_rng(seed)
    a, vel = random_pose(rng), random_velocity(rng)
    g, h = random_pose(rng), random_pose(rng)
    want = compose(compose(g, twist_extrapolate(a, vel, dt)), h)
    ga = compose(g, a)
    gv = world_velocity(g, vel)
    got = twist_extrapolate(compose(ga, h), body_velocity(ga, h, gv), dt)
    assert_same_poses(got, want, 1e-10)


def test_twist_extrapolation_small_angles_match_the_screw() -> None:
    """Near zero and around the series switch, dead reckoning still equals ScLERP continued."""
    a = np.array([0.1, 0.2, 0.3, 0.6, 0.0, 0.8, 0.0])
    dt = 0.1
    for w in (0.0, 1e-12, 1e-8, 1e-5, 0.999e-3 / dt, 1.001e-3 / dt, 0.05):
        vel = np.array([1.0, -2.0, 0.5, w, 0.3 * w, -w])
        b = twist_extrapolate(a, vel, dt)
        for s in (0.3, 1.0, 1.7):
            want = interp.screw_extrapolate(a, b, s, max_s=2.0)
            assert_same_poses(twist_extrapolate(a, vel, s * dt), want, 1e-13)
        assert abs(float(np.linalg.norm(b[3:])) - 1.0) <= 1e-15


# --- exact half turns ---------------------------------------------------------------------


@pytest.mark.parametrize("method", ["motor-cubic", "motor-hermite"])
def test_sign_blindness_at_an_exact_half_turn(method: str) -> None:
    """Negating a keyframe 180 degrees from its neighbour should not change the curve."""
    a = np.array([0.0, 0.0, 0.0, 0.5, -0.5, 0.5, 0.5])
    b = np.array([0.0, 0.0, 1.0, 0.0, 0.0, np.sqrt(0.5), -np.sqrt(0.5)])
    b_neg = np.concatenate([b[:3], -b[3:]])
    zero = np.zeros(6)
    if method == "motor-cubic":
        t = np.array([0.0, 0.0, 1.0, 1.0])
        got = interp.motor_cubic(np.stack([a, a, b_neg, b_neg]), t, 0.5)
        want = interp.motor_cubic(np.stack([a, a, b, b]), t, 0.5)
    else:
        got = interp.motor_hermite(a, b_neg, zero, zero, 1.0, 0.5)
        want = interp.motor_hermite(a, b, zero, zero, 1.0, 0.5)
    assert_same_poses(got, want)


def test_motor_cubic_chunks_do_not_change_results() -> None:
    """A batch over several of motor_cubic's chunks equals its pieces, bit for bit."""
    rng = np.random.default_rng(4)
    n = 9001
    q = _unit(rng.normal(size=(n, 4, 4)))
    keys = np.concatenate([rng.uniform(-2.0, 2.0, (n, 4, 3)), q], axis=-1)
    times = np.cumsum(rng.uniform(0.02, 0.2, (n, 4)), axis=-1)
    times[::7, 0] = times[::7, 1]  # missing neighbours on some windows
    t = times[:, 1] + rng.uniform(0.0, 1.0, n) * (times[:, 2] - times[:, 1])
    whole = interp.motor_cubic(keys, times, t)
    cuts = [0, 1, 2, 4095, 4096, 4097, 8200, n]
    parts = [interp.motor_cubic(keys[i:j], times[i:j], t[i:j]) for i, j in itertools.pairwise(cuts)]
    np.testing.assert_array_equal(whole, np.concatenate(parts))
