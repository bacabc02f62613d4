"""soa-hermite: cubic Hermite position + quaternion Hermite rotation from velocities.

Exact keyframes, sign blindness, unit outputs, degenerate and half-turn inputs,
the motions it must reproduce exactly (constant linear velocity, constant
angular velocity about a fixed axis), its end velocities, its limit against
motor-hermite for pure translation, and its place in the registry and the CLI.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray

from posecast import interp
from posecast.interp.extrapolate import twist_extrapolate
from posecast.interp.hermite import soa_hermite

F64 = NDArray[np.float64]

PROPERTY_SETTINGS = settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
seeds = st.integers(0, 2**32 - 1)
fraction = st.floats(0.0, 1.0, allow_nan=False)


def _unit(v: F64) -> F64:
    out: F64 = v / np.linalg.norm(v, axis=-1, keepdims=True)
    return out


def random_pose(rng: np.random.Generator) -> F64:
    return np.concatenate([rng.uniform(-2.0, 2.0, 3), _unit(rng.normal(size=4))])


def random_velocity(rng: np.random.Generator, lin: float = 3.0, ang: float = 6.0) -> F64:
    return np.concatenate([rng.uniform(-lin, lin, 3), rng.uniform(-ang, ang, 3)])


def keyframe_pair(seed: int) -> tuple[F64, F64, F64, F64, float]:
    """Two keyframes a random motion apart, random velocities and the interval."""
    rng = np.random.default_rng(seed)
    dt = float(rng.uniform(0.03, 0.2))
    a = random_pose(rng)
    b = twist_extrapolate(a, random_velocity(rng, 3.0, 10.0), dt)
    return a, b, random_velocity(rng), random_velocity(rng), dt


def angle(q0: F64, q1: F64) -> F64:
    """Angle between rotations (rad), sign-blind."""
    q1 = q1 * np.where(np.sum(q0 * q1, axis=-1) < 0.0, -1.0, 1.0)[..., None]
    out: F64 = 4.0 * np.arctan2(np.linalg.norm(q1 - q0, axis=-1), np.linalg.norm(q1 + q0, axis=-1))
    return out


def assert_same_poses(got: F64, want: F64, tol: float = 1e-12) -> None:
    dp = float(np.max(np.linalg.norm(got[..., :3] - want[..., :3], axis=-1)))
    dq = float(np.max(angle(got[..., 3:], want[..., 3:])))
    assert dp <= tol, f"positions differ by {dp:.3g} m"
    assert dq <= tol, f"rotations differ by {dq:.3g} rad"


def axis_rotation(axis: F64, theta: float | F64) -> F64:
    """Quaternion(s) of a rotation by ``theta`` about the unit ``axis``."""
    th = np.asarray(theta, dtype=np.float64)[..., None]
    return np.concatenate([np.cos(0.5 * th), np.sin(0.5 * th) * axis], axis=-1)


def curve(a: F64, b: F64, va: F64, vb: F64, dt: float, s: F64) -> F64:
    """soa-hermite at several fractions ``s`` of one keyframe pair."""
    n = (*np.shape(s), 7)
    return soa_hermite(np.broadcast_to(a, n), np.broadcast_to(b, n), va, vb, dt, s)


# --- registry and CLI ----------------------------------------------------------------


def test_registered_as_a_velocity_method_like_motor_hermite() -> None:
    """Same kind, velocity need and look-ahead as motor-hermite; not body-frame invariant."""
    mine, ref = interp.info("soa-hermite"), interp.info("motor-hermite")
    assert mine.func is soa_hermite
    assert (mine.kind, mine.needs_velocity, mine.lookahead, mine.lookbehind) == (
        ref.kind,
        ref.needs_velocity,
        ref.lookahead,
        ref.lookbehind,
    )
    assert mine.kind == "velocity" and mine.needs_velocity
    assert not mine.frame_invariant
    assert "soa-hermite" in interp.names()


def test_posecast_interpolators_lists_it() -> None:
    """`posecast interpolators` prints soa-hermite beside motor-hermite."""
    from typer.testing import CliRunner

    from posecast.cli import app

    res = CliRunner().invoke(app, ["interpolators"])
    assert res.exit_code == 0, res.output
    assert "soa-hermite" in res.output and "motor-hermite" in res.output


def test_track_evaluation_runs_it_like_motor_hermite() -> None:
    """evaluate_track takes it by name with keyframe velocities, as it does motor-hermite."""
    rng = np.random.default_rng(3)
    times = np.array([0.0, 0.1, 0.25])
    poses = np.stack([random_pose(rng) for _ in range(3)])[:, None]
    vel = np.stack([random_velocity(rng) for _ in range(3)])[:, None]
    query = np.linspace(0.0, 0.25, 11)
    got = interp.evaluate_track(times, poses, query, "soa-hermite", velocities=vel).poses
    assert got.shape == (11, 1, 7)
    np.testing.assert_array_equal(got[0, 0], poses[0, 0])
    np.testing.assert_array_equal(got[-1, 0], poses[2, 0])
    k = 5  # 0.125: inside the second interval
    s = (query[k] - 0.1) / 0.15
    want = soa_hermite(poses[1, 0], poses[2, 0], vel[1, 0], vel[2, 0], 0.15, s)
    np.testing.assert_allclose(got[k, 0], want, rtol=0, atol=1e-12)


# --- exactness, signs, units -----------------------------------------------------------


@PROPERTY_SETTINGS
@given(seed=seeds)
def test_endpoints_are_the_keyframes_bit_for_bit(seed: int) -> None:
    """s = 0 gives a and s = 1 gives b exactly, also in a batch."""
    a, b, va, vb, dt = keyframe_pair(seed)
    np.testing.assert_array_equal(soa_hermite(a, b, va, vb, dt, 0.0), a)
    np.testing.assert_array_equal(soa_hermite(a, b, va, vb, dt, 1.0), b)
    both = soa_hermite(np.stack([a, a]), np.stack([b, b]), va, vb, dt, np.array([0.0, 1.0]))
    np.testing.assert_array_equal(both, np.stack([a, b]))


@PROPERTY_SETTINGS
@given(seed=seeds, s=fraction)
def test_endpoints_are_approached_continuously(seed: int, s: float) -> None:
    """Just inside the interval the curve is within ~|velocity| ds of the keyframes."""
    a, b, va, vb, dt = keyframe_pair(seed)
    eps = 1e-9
    assert_same_poses(soa_hermite(a, b, va, vb, dt, eps), a, 1e-7)
    assert_same_poses(soa_hermite(a, b, va, vb, dt, 1.0 - eps), b, 1e-7)


@PROPERTY_SETTINGS
@given(seed=seeds, s=fraction, which=st.integers(1, 3))
def test_negated_quaternions_give_the_same_poses(seed: int, s: float, which: int) -> None:
    """q and -q of either keyframe (or both) give the same pose."""
    a, b, va, vb, dt = keyframe_pair(seed)
    want = soa_hermite(a, b, va, vb, dt, s)
    a2, b2 = a.copy(), b.copy()
    if which & 1:
        a2[3:] *= -1.0
    if which & 2:
        b2[3:] *= -1.0
    got = soa_hermite(a2, b2, va, vb, dt, s)
    np.testing.assert_array_equal(got[:3], want[:3])
    assert_same_poses(got, want, 1e-14)


@PROPERTY_SETTINGS
@given(seed=seeds, s=fraction)
def test_outputs_have_unit_quaternions(seed: int, s: float) -> None:
    a, b, va, vb, dt = keyframe_pair(seed)
    out = soa_hermite(a, b, 10.0 * va, 10.0 * vb, dt, s)
    assert out.shape == (7,)
    assert abs(float(np.linalg.norm(out[3:])) - 1.0) <= 1e-15


def test_exact_half_turn_tie_is_broken_by_rotation_not_sign() -> None:
    """At q_a . q_b == 0 the path does not depend on the quaternions' signs."""
    a = np.array([0.0, 0.0, 0.0, 0.5, -0.5, 0.5, 0.5])
    b = np.array([0.0, 0.0, 1.0, 0.0, 0.0, np.sqrt(0.5), -np.sqrt(0.5)])
    assert np.dot(a[3:], b[3:]) == 0.0
    va = np.array([0.1, 0.0, 0.0, 0.3, -0.2, 1.0])
    vb = np.array([0.0, 0.2, 0.0, -0.5, 0.4, 0.1])
    want = soa_hermite(a, b, va, vb, 0.1, 0.3)
    flip = np.array([1, 1, 1, -1, -1, -1, -1.0])
    for x, y in ((a * flip, b), (a, b * flip), (a * flip, b * flip)):
        assert_same_poses(soa_hermite(x, y, va, vb, 0.1, 0.3), want, 1e-15)


# --- degenerate and extreme rotations ----------------------------------------------------


@pytest.mark.parametrize("theta", [0.0, 1e-300, 1e-12, 1e-7, 1e-3, 9.99e-3, 1e-2, 0.1])
def test_tiny_and_zero_rotations_stay_finite_and_smooth(theta: float) -> None:
    """Tiny relative rotations (and none) give finite unit poses, continuous in the angle."""
    rng = np.random.default_rng(7)
    a = random_pose(rng)
    axis = _unit(np.array([0.3, -0.5, 0.8]))
    b = a.copy()
    b[:3] += [0.1, 0.2, -0.1]
    b[3:] = interp.quat_mul(a[3:], axis_rotation(axis, theta))
    va = np.array([1.0, 0.0, 0.0, *(theta * 5.0 * axis)])
    vb = np.array([0.0, 1.0, 0.0, 0.0, 0.0, 0.0])
    s = np.linspace(0.0, 1.0, 17)
    out = curve(a, b, va, vb, 0.2, s)
    assert np.all(np.isfinite(out))
    np.testing.assert_allclose(np.linalg.norm(out[:, 3:], axis=1), 1.0, rtol=0, atol=1e-15)
    # Rotation stays within a few theta of a (the end tangent is at most 5 theta / s).
    assert np.all(angle(out[:, 3:], np.broadcast_to(a[3:], (17, 4))) <= 2.0 * theta + 1e-15)


@pytest.mark.parametrize("gap", [0.0, 1e-15, 1e-9, 1e-6, 1e-3])
def test_near_half_turn_is_finite_and_continuous(gap: float) -> None:
    """Relative rotations of pi - gap give finite unit poses close to the half turn's."""
    rng = np.random.default_rng(11)
    a = random_pose(rng)
    axis = _unit(np.array([0.2, 0.9, -0.4]))
    va = np.array([0.0, 0.0, 0.0, 0.7, -0.3, 0.2])
    vb = np.array([0.0, 0.0, 0.0, -0.1, 0.5, 0.4])
    s = np.linspace(0.0, 1.0, 9)

    def run(g: float) -> F64:
        b = a.copy()
        b[3:] = interp.quat_mul(a[3:], axis_rotation(axis, np.pi - g))
        return curve(a, b, va, vb, 0.1, s)

    got, ref = run(gap), run(1e-12)
    assert np.all(np.isfinite(got))
    np.testing.assert_allclose(np.linalg.norm(got[:, 3:], axis=1), 1.0, rtol=0, atol=1e-15)
    # The curve moves continuously with the keyframe (Lipschitz in the gap).
    assert float(np.max(angle(got[:, 3:], ref[:, 3:]))) <= 10.0 * gap + 1e-9


# --- motions it reproduces -----------------------------------------------------------------


@pytest.mark.parametrize("turn", [0.0, 1e-8, 0.3, 1.5, 3.0, 3.1])
def test_constant_angular_velocity_about_a_fixed_axis_is_reproduced(turn: float) -> None:
    """Rotation at constant omega (any angle per interval below pi) with matching end
    velocities, and constant linear velocity, are reproduced to 1e-9."""
    rng = np.random.default_rng(int(turn * 1000) + 1)
    dt = 0.08
    axis = _unit(rng.normal(size=3))
    omega = axis * (turn / dt)
    v = rng.uniform(-2.0, 2.0, 3)
    a = random_pose(rng)
    s = np.linspace(0.0, 1.0, 41)

    def truth(t: F64) -> F64:
        q = interp.quat_mul(axis_rotation(axis, t * turn / dt), np.broadcast_to(a[3:], (t.size, 4)))
        return np.concatenate([a[:3] + t[:, None] * v, q], axis=-1)

    b = truth(np.array([dt]))[0]
    vel = np.concatenate([v, omega])
    got = curve(a, b, vel, vel, dt, s)
    assert_same_poses(got, truth(s * dt), 1e-9)


@PROPERTY_SETTINGS
@given(seed=seeds, s=fraction)
def test_constant_linear_velocity_is_reproduced(seed: int, s: float) -> None:
    """p_b = p_a + v dt with v at both ends: the position is p_a + v s dt, whatever rotates."""
    a, b, va, vb, dt = keyframe_pair(seed)
    v = va[:3]
    b[:3] = a[:3] + v * dt
    vb[:3] = v
    got = soa_hermite(a, b, va, vb, dt, s)
    np.testing.assert_allclose(got[:3], a[:3] + v * s * dt, rtol=0, atol=1e-12)


@PROPERTY_SETTINGS
@given(seed=seeds, s=fraction)
def test_zero_velocities_ease_along_the_soa_path(seed: int, s: float) -> None:
    """With zero velocities it is SoA at the smoothstep fraction 3s^2 - 2s^3."""
    a, b, _, _, dt = keyframe_pair(seed)
    zero = np.zeros(6)
    got = soa_hermite(a, b, zero, zero, dt, s)
    assert_same_poses(got, interp.soa(a, b, s * s * (3.0 - 2.0 * s)), 1e-12)


def test_identical_keyframes_with_zero_velocities_hold() -> None:
    a = np.array([0.5, -1.0, 2.0, 0.5, 0.5, -0.5, 0.5])
    out = curve(a, a, np.zeros(6), np.zeros(6), 0.1, np.linspace(0, 1, 7))
    assert_same_poses(out, np.broadcast_to(a, (7, 7)), 1e-15)


@PROPERTY_SETTINGS
@given(seed=seeds)
def test_end_velocities_are_the_reported_ones(seed: int) -> None:
    """d/dt of the curve at s = 0 and s = 1 is (v_a, omega_a) and (v_b, omega_b)."""
    a, b, va, vb, dt = keyframe_pair(seed)
    h = 1e-6
    s = np.array([0.0, h, 2 * h, 1.0 - 2 * h, 1.0 - h, 1.0])
    p = curve(a, b, va, vb, dt, s)
    q = p[:, 3:] * np.where(p[:, 3:] @ p[0, 3:] < 0, -1.0, 1.0)[:, None]
    # Second-order one-sided differences in time.
    d0 = (-3 * q[0] + 4 * q[1] - q[2]) / (2 * h * dt)
    d1 = (3 * q[5] - 4 * q[4] + q[3]) / (2 * h * dt)
    w0 = 2.0 * interp.quat_mul(d0, interp.quat_conj(q[0]))[1:]
    w1 = 2.0 * interp.quat_mul(d1, interp.quat_conj(q[5]))[1:]
    np.testing.assert_allclose(w0, va[3:], rtol=0, atol=1e-5 * (1 + np.abs(va[3:]).max()))
    np.testing.assert_allclose(w1, vb[3:], rtol=0, atol=1e-5 * (1 + np.abs(vb[3:]).max()))
    v0 = (-3 * p[0, :3] + 4 * p[1, :3] - p[2, :3]) / (2 * h * dt)
    v1 = (3 * p[5, :3] - 4 * p[4, :3] + p[3, :3]) / (2 * h * dt)
    np.testing.assert_allclose(v0, va[:3], rtol=0, atol=1e-5)
    np.testing.assert_allclose(v1, vb[:3], rtol=0, atol=1e-5)


# --- frames and motor-hermite ---------------------------------------------------------------


@PROPERTY_SETTINGS
@given(seed=seeds, s=fraction)
def test_world_frame_change_commutes(seed: int, s: float) -> None:
    """G f(a, b) == f(G a, G b) with the velocities rotated by G."""
    a, b, va, vb, dt = keyframe_pair(seed)
    g = random_pose(np.random.default_rng(seed + 1))

    def move(p: F64) -> F64:
        t = g[:3] + interp.quat_rotate(g[3:], p[:3])
        return np.concatenate([t, interp.quat_mul(g[3:], p[3:])])

    def turn(v: F64) -> F64:
        return np.concatenate([interp.quat_rotate(g[3:], v[:3]), interp.quat_rotate(g[3:], v[3:])])

    got = soa_hermite(move(a), move(b), turn(va), turn(vb), dt, s)
    assert_same_poses(got, move(soa_hermite(a, b, va, vb, dt, s)), 1e-11)


@PROPERTY_SETTINGS
@given(seed=seeds, s=fraction)
def test_pure_translation_is_motor_hermite(seed: int, s: float) -> None:
    """Same rotation at both keyframes and no angular velocity: the two curves agree."""
    a, b, va, vb, dt = keyframe_pair(seed)
    b[3:] = a[3:]
    va[3:] = vb[3:] = 0.0
    want = interp.motor_hermite(a, b, va, vb, dt, s)
    assert_same_poses(soa_hermite(a, b, va, vb, dt, s), want, 1e-12)


def test_agrees_with_motor_hermite_in_the_limit_of_no_rotation() -> None:
    """With rotation scaled by eps the difference from motor-hermite shrinks like eps."""
    rng = np.random.default_rng(5)
    a, dt = random_pose(rng), 0.1
    lin = rng.uniform(-2.0, 2.0, 3)
    wa, wb, axis = rng.normal(size=3), rng.normal(size=3), _unit(rng.normal(size=3))
    s = np.linspace(0.0, 1.0, 21)
    gaps = []
    for eps in (1e-2, 1e-4, 1e-6):
        b = a.copy()
        b[:3] += lin * dt
        b[3:] = interp.quat_mul(axis_rotation(axis, eps), a[3:])
        va, vb = np.r_[lin, eps * wa], np.r_[lin, eps * wb]
        n = (s.size, 7)
        want = interp.motor_hermite(np.broadcast_to(a, n), np.broadcast_to(b, n), va, vb, dt, s)
        got = curve(a, b, va, vb, dt, s)
        dp = np.linalg.norm(got[:, :3] - want[:, :3], axis=1)
        gaps.append(float(np.max(dp + angle(got[:, 3:], want[:, 3:]))))
    assert gaps[1] <= 2e-2 * gaps[0] and gaps[2] <= 2e-2 * gaps[1] + 1e-12
    assert gaps[2] <= 1e-6


def test_bad_inputs_are_rejected_like_motor_hermite() -> None:
    a = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    v = np.zeros(6)
    for f in (soa_hermite, interp.motor_hermite):
        with pytest.raises(ValueError, match="dt"):
            f(a, a, v, v, 0.0, 0.5)
        with pytest.raises(ValueError, match="shape"):
            f(a, a, np.zeros(5), v, 0.1, 0.5)
        with pytest.raises(ValueError, match="finite"):
            f(a, a, np.full(6, np.nan), v, 0.1, 0.5)


@pytest.mark.parametrize("theta", [1e-8, 5e-3, 9.99e-3, 1.001e-2, 0.5, 2.0, 3.0, np.pi])
def test_inverse_right_jacobian_matches_the_inverted_closed_form(theta: float) -> None:
    """J_r^-1(r) w against solve(J_r(r), w), on both sides of the series switch."""
    from posecast.interp.hermite import _dexp_inv

    axis = _unit(np.array([0.6, -0.2, 0.7]))
    r = axis * theta
    rel = axis_rotation(axis, theta)
    w = np.array([0.3, 1.1, -0.8])
    big = np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
    c1 = (1.0 - np.cos(theta)) / theta**2 if theta > 1e-4 else 0.5
    c2 = (theta - np.sin(theta)) / theta**3 if theta > 1e-4 else 1.0 / 6.0
    jac = np.eye(3) - c1 * big + c2 * (big @ big)
    got = _dexp_inv(r[:, None], rel[:, None], w[:, None])[:, 0]
    np.testing.assert_allclose(got, np.linalg.solve(jac, w), rtol=0, atol=1e-10)
