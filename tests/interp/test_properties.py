"""Invariants of the three interpolators, checked with hypothesis.

Endpoints, sign blindness, unit outputs, degenerate inputs, frame changes,
motor LERP vs ScLERP and quaternion NLERP, and ScLERP's constant screw.

A change of *world* frame is ``G a`` (left product): it moves the whole scene.
A change of *body* frame is ``a H`` (right product): it moves the tracked point
on the device (grip vs tool tip). ScLERP and motor LERP commute with both; SoA
commutes with the first (a rigid G maps LERP to LERP and SLERP to SLERP) and
not with the second, which is where SoA's swing of an off-centre point shows.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray

from posecast import interp

F64 = NDArray[np.float64]

METHODS = ("soa", "dq-slerp", "motor-lerp")
RIGID_METHODS = ("dq-slerp", "motor-lerp")
# No deadline and no "too slow" check: the suite shares its machine with other
# jobs, and a slow example is not a wrong one.
PROPERTY_SETTINGS = settings(
    max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)

# --- strategies -----------------------------------------------------------------

coordinate = st.floats(-5.0, 5.0, allow_nan=False, allow_infinity=False)
fraction = st.floats(0.0, 1.0, allow_nan=False, allow_infinity=False)
method = st.sampled_from(METHODS)
rigid_method = st.sampled_from(RIGID_METHODS)


@st.composite
def unit_quaternions(draw: st.DrawFn) -> F64:
    """Unit quaternions (w first) from non-degenerate 4-vectors."""
    raw = np.array(draw(st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4)))
    n = float(np.linalg.norm(raw))
    if n < 0.1:  # too short to give a well-spread direction: use a fixed one
        raw, n = np.array([0.5, -0.5, 0.5, 0.5]), 1.0
    out: F64 = raw / n
    return out


@st.composite
def poses(draw: st.DrawFn) -> F64:
    """One pose ``(7,)``: position within 5 m per axis, unit quaternion."""
    t = np.array(draw(st.lists(coordinate, min_size=3, max_size=3)))
    return np.concatenate([t, draw(unit_quaternions())])


tiny_angle = st.sampled_from([0.0, 5e-324, 1e-300, 1e-200, 1e-20, 1e-16, 1e-12, 1e-9, 1e-7])

# --- helpers --------------------------------------------------------------------


def rotation_angle(q0: F64, q1: F64) -> F64:
    """Angle in rad between unit quaternion rotations, blind to their sign."""
    q1 = q1 * np.where(np.sum(q0 * q1, axis=-1) < 0.0, -1.0, 1.0)[..., None]
    d = np.linalg.norm(q1 - q0, axis=-1)
    m = np.linalg.norm(q1 + q0, axis=-1)
    out: F64 = 4.0 * np.arctan2(d, m)
    return out


def assert_same_poses(got: F64, want: F64, scale: float, tol: float = 1e-12) -> None:
    """Positions within ``tol * max(1, scale)`` m, rotations within ``tol`` rad."""
    dp = float(np.max(np.linalg.norm(got[..., :3] - want[..., :3], axis=-1)))
    dq = float(np.max(rotation_angle(got[..., 3:], want[..., 3:])))
    assert dp <= tol * max(1.0, scale), f"positions differ by {dp:.3g} m"
    assert dq <= tol, f"rotations differ by {dq:.3g} rad"


def translation_scale(a: F64, b: F64) -> float:
    """The larger of the two keyframes' distances from the origin, in m."""
    return float(np.max(np.linalg.norm(np.stack([a[:3], b[:3]]), axis=1)))


def not_half_turn(a: F64, b: F64) -> bool:
    """Whether a and b are clearly not 180 deg apart, where the short way is a tie.

    At a tie, the rounding of a frame change decides which way round each side
    goes; that is not a failure of the property.
    """
    return bool(abs(np.dot(a[3:], b[3:])) > 1e-6)


def compose(g: F64, a: F64) -> F64:
    """Rigid product ``g a`` of poses: ``(t_g + R_g t_a, q_g q_a)``."""
    t = g[..., :3] + interp.quat_rotate(g[..., 3:], a[..., :3])
    return np.concatenate([t, interp.quat_mul(g[..., 3:], a[..., 3:])], axis=-1)


def with_rotation_by(a: F64, axis: F64, angle: float) -> F64:
    """Quaternion ``q_a (cos(angle/2), sin(angle/2) axis)`` (a relative rotation)."""
    half = 0.5 * angle
    rel = np.concatenate([[np.cos(half)], np.sin(half) * axis / np.linalg.norm(axis)])
    out: F64 = interp.quat_mul(a[3:], rel)
    return out


def twist_exp(omega: F64, v: F64) -> F64:
    """Pose ``exp([omega, v])`` of a body twist: rotation ``exp(omega)``, ``t = V v``.

    ``V = I + (1 - cos th)/th^2 W + (th - sin th)/th^3 W^2`` with ``W = [omega]x``;
    for ``th < 1e-4`` the coefficients use their Taylor series (error < 1e-17).
    """
    th = float(np.linalg.norm(omega))
    w = np.array(
        [[0.0, -omega[2], omega[1]], [omega[2], 0.0, -omega[0]], [-omega[1], omega[0], 0.0]]
    )
    th2 = th * th
    if th < 1e-4:
        c1 = 0.5 - th2 / 24.0
        c2 = 1.0 / 6.0 - th2 / 120.0
        sinc_half = 0.5 - th2 / 48.0  # sin(th/2)/th
    else:
        c1 = (1.0 - np.cos(th)) / th2
        c2 = (th - np.sin(th)) / (th2 * th)
        sinc_half = np.sin(0.5 * th) / th
    t = v + c1 * (w @ v) + c2 * (w @ (w @ v))
    q = np.concatenate([[np.cos(0.5 * th)], sinc_half * omega])
    return np.concatenate([t, q])


# --- endpoints, sign, units ------------------------------------------------------


@PROPERTY_SETTINGS
@given(name=method, a=poses(), b=poses())
def test_endpoints_reproduce_keyframes_exactly(name: str, a: F64, b: F64) -> None:
    """f(a, b, 0) is a and f(a, b, 1) is b, bit for bit."""
    f = interp.get(name)
    np.testing.assert_array_equal(f(a, b, 0.0), a)
    np.testing.assert_array_equal(f(a, b, 1.0), b)
    both = f(np.stack([a, a]), np.stack([b, b]), np.array([0.0, 1.0]))
    np.testing.assert_array_equal(both, np.stack([a, b]))


@PROPERTY_SETTINGS
@given(name=method, a=poses(), b=poses(), s=fraction)
def test_negated_quaternions_give_the_same_poses(name: str, a: F64, b: F64, s: float) -> None:
    """Negating either keyframe's quaternion (same rotation) leaves the result unchanged."""
    f = interp.get(name)
    want = f(a, b, s)
    a_neg, b_neg = a.copy(), b.copy()
    a_neg[3:] *= -1.0
    b_neg[3:] *= -1.0
    # At exactly 180 deg (q0.q1 == 0) both ways round are equally short and the
    # sign of the zero decides: a tie, not a property violation.
    assume(not_half_turn(a, b))
    scale = translation_scale(a, b)
    for x, y in ((a_neg, b), (a, b_neg), (a_neg, b_neg)):
        assert_same_poses(f(x, y, s), want, scale)


@PROPERTY_SETTINGS
@given(name=method, a=poses(), b=poses(), s=fraction)
def test_outputs_have_unit_quaternions(name: str, a: F64, b: F64, s: float) -> None:
    """The output quaternion has unit norm to 1e-15 relative."""
    out = interp.get(name)(a, b, s)
    assert out.shape == (7,)
    assert abs(float(np.linalg.norm(out[3:])) - 1.0) <= 1e-15


@PROPERTY_SETTINGS
@given(
    name=method,
    a=poses(),
    axis=st.lists(st.floats(0.1, 1.0), min_size=3, max_size=3),
    angle=tiny_angle,
    dt=st.lists(coordinate, min_size=3, max_size=3),
    negate=st.booleans(),
    s=fraction,
)
def test_tiny_and_zero_rotations_stay_finite(
    name: str, a: F64, axis: list[float], angle: float, dt: list[float], negate: bool, s: float
) -> None:
    """Relative rotations from 0 to 1e-7 rad (also pure translations) give finite unit poses."""
    b = a.copy()
    b[:3] += np.array(dt)
    b[3:] = with_rotation_by(a, np.array(axis), angle) * (-1.0 if negate else 1.0)
    out = interp.get(name)(a, b, s)
    assert np.all(np.isfinite(out))
    assert abs(float(np.linalg.norm(out[3:])) - 1.0) <= 1e-15
    # A (nearly) pure translation moves along the segment from a to b: a screw
    # strays from it by at most about angle * |dt|.
    scale = max(1.0, translation_scale(a, b))
    off_segment = np.linalg.norm(out[:3] - (a[:3] + s * (b[:3] - a[:3])))
    assert off_segment <= 1e-12 * scale + angle * float(np.linalg.norm(dt))
    assert float(rotation_angle(out[3:], a[3:])) <= angle + 4e-15


@PROPERTY_SETTINGS
@given(name=method, a=poses(), s=fraction, ulps=st.integers(1, 8), k=st.integers(0, 3))
def test_ulp_sized_quaternion_differences_stay_finite(
    name: str, a: F64, s: float, ulps: int, k: int
) -> None:
    """Quaternions a few ulp apart (non-unit by rounding) give finite poses."""
    b = a.copy()
    for _ in range(ulps):
        b[3 + k] = np.nextafter(b[3 + k], np.inf)
    out = interp.get(name)(a, b, s)
    assert np.all(np.isfinite(out))
    assert float(rotation_angle(out[3:], a[3:])) <= 1e-14


# --- frame changes -----------------------------------------------------------------


@PROPERTY_SETTINGS
@given(name=method, a=poses(), b=poses(), g=poses(), s=fraction)
def test_world_frame_change_commutes(name: str, a: F64, b: F64, g: F64, s: float) -> None:
    """G f(a, b, s) == f(G a, G b, s) for a rigid G (SoA included: see module docstring)."""
    assume(not_half_turn(a, b))
    f = interp.get(name)
    scale = float(np.linalg.norm(g[:3])) + translation_scale(a, b)
    assert_same_poses(f(compose(g, a), compose(g, b), s), compose(g, f(a, b, s)), scale, 1e-11)


@PROPERTY_SETTINGS
@given(name=rigid_method, a=poses(), b=poses(), h=poses(), s=fraction)
def test_rigid_methods_commute_with_body_frame_change(
    name: str, a: F64, b: F64, h: F64, s: float
) -> None:
    """f(a, b, s) H == f(a H, b H, s) for dq-slerp and motor-lerp."""
    assume(not_half_turn(a, b))
    f = interp.get(name)
    scale = float(np.linalg.norm(h[:3])) + translation_scale(a, b)
    assert_same_poses(f(compose(a, h), compose(b, h), s), compose(f(a, b, s), h), scale, 1e-11)


def test_soa_does_not_commute_with_body_frame_change() -> None:
    """SoA of an off-centre point is not SoA of the grip moved to it: a counterexample."""
    # A hand turning 90 deg about y while staying put; the tracked point is 0.2 m
    # along -z (a tool tip). Rigid methods swing the tip on the circle; SoA cuts
    # the chord, so the tip comes 0.2 (1 - cos 45 deg) = 58.6 mm too close.
    a = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    b = np.array([0.0, 0.0, 0.0, np.cos(np.pi / 4), 0.0, np.sin(np.pi / 4), 0.0])
    tip = np.array([0.0, 0.0, -0.2, 1.0, 0.0, 0.0, 0.0])
    moved_after = compose(interp.soa(a, b, 0.5), tip)
    moved_before = interp.soa(compose(a, tip), compose(b, tip), 0.5)
    assert np.isclose(np.linalg.norm(moved_after[:3]), 0.2, rtol=1e-15)
    assert np.isclose(np.linalg.norm(moved_before[:3]), 0.2 * np.cos(np.pi / 4), rtol=1e-15)
    gap = np.linalg.norm(moved_after[:3] - moved_before[:3])
    assert np.isclose(gap, 0.2 * (1.0 - np.cos(np.pi / 4)), rtol=1e-14)
    for name in RIGID_METHODS:
        f = interp.get(name)
        assert_same_poses(f(compose(a, tip), compose(b, tip), 0.5), compose(f(a, b, 0.5), tip), 1.0)


# --- motor LERP vs ScLERP and NLERP; constant screw ------------------------------------


@PROPERTY_SETTINGS
@given(a=poses(), b=poses())
def test_motor_lerp_equals_dq_slerp_at_half(a: F64, b: F64) -> None:
    """motor-lerp(a, b, 1/2) == dq-slerp(a, b, 1/2)."""
    scale = translation_scale(a, b)
    assert_same_poses(interp.motor_lerp(a, b, 0.5), interp.dq_slerp(a, b, 0.5), scale)


@PROPERTY_SETTINGS
@given(a=poses(), b=poses(), s=fraction)
def test_motor_lerp_rotation_is_quaternion_nlerp(a: F64, b: F64, s: float) -> None:
    """motor-lerp's rotation is the normalised LERP of q0 and q1 (in q0's hemisphere)."""
    q0, q1 = a[3:], b[3:] * (1.0 if np.dot(a[3:], b[3:]) >= 0.0 else -1.0)
    nlerp = (1.0 - s) * q0 + s * q1
    nlerp /= np.linalg.norm(nlerp)
    assert float(rotation_angle(interp.motor_lerp(a, b, s)[3:], nlerp)) <= 1e-12


@PROPERTY_SETTINGS
@given(
    omega=st.lists(st.floats(-1.8, 1.8), min_size=3, max_size=3),
    v=st.lists(coordinate, min_size=3, max_size=3),
    g=poses(),
    s=fraction,
)
def test_dq_slerp_follows_a_constant_screw(
    omega: list[float], v: list[float], g: F64, s: float
) -> None:
    """dq-slerp(exp(0), exp(xi), s) == exp(s xi), also started from any pose G."""
    w, u = np.array(omega), np.array(v)  # |omega| < pi: the screw is the short way
    identity = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    end, want = twist_exp(w, u), twist_exp(s * w, s * u)
    scale = float(np.linalg.norm(end[:3]))
    assert_same_poses(interp.dq_slerp(identity, end, s), want, scale)
    got = interp.dq_slerp(g, compose(g, end), s)
    assert_same_poses(got, compose(g, want), scale + float(np.linalg.norm(g[:3])), 1e-11)


@pytest.mark.parametrize("name", ["soa", "dq-slerp", "motor-lerp"])
def test_exact_half_turn_tie_is_broken_by_rotation_not_sign(name: str) -> None:
    """At q0.q1 == 0 the path chosen does not depend on the quaternions' signs."""
    a = np.array([0.0, 0.0, 0.0, 0.5, -0.5, 0.5, 0.5])
    b = np.array([0.0, 0.0, 1.0, 0.0, 0.0, np.sqrt(0.5), -np.sqrt(0.5)])
    assert np.dot(a[3:], b[3:]) == 0.0
    f = interp.get(name)
    want = f(a, b, 0.3)
    flip = np.array([1, 1, 1, -1, -1, -1, -1.0])
    for x, y in ((a * flip, b), (a, b * flip), (a * flip, b * flip)):
        assert_same_poses(f(x, y, 0.3), want, 1.0)
