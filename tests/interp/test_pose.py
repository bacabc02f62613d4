"""Pose conversions, quaternion algebra and input validation of ``interp``."""

from __future__ import annotations

import re

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from posecast import interp

F64 = NDArray[np.float64]

METHODS = ("soa", "dq-slerp", "motor-lerp")


def random_poses(seed: int, n: int = 1000, extent: float = 3.0) -> F64:
    """Seeded poses: positions within ``extent`` m per axis, uniform unit quaternions."""
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.concatenate([rng.uniform(-extent, extent, (n, 3)), q], axis=1)


def rotation_angle(q0: F64, q1: F64) -> F64:
    """Angle in rad between unit quaternion rotations, blind to their sign."""
    q1 = q1 * np.where(np.sum(q0 * q1, axis=-1) < 0.0, -1.0, 1.0)[..., None]
    out: F64 = 4.0 * np.arctan2(np.linalg.norm(q1 - q0, axis=-1), np.linalg.norm(q1 + q0, axis=-1))
    return out


def xyzw(q: F64) -> F64:
    """w-first quaternions to scipy's scalar-last order."""
    return q[..., [1, 2, 3, 0]]


def wxyz(q: F64) -> F64:
    """scipy's scalar-last quaternions to w first."""
    return q[..., [3, 0, 1, 2]]


# --- round trips ----------------------------------------------------------------


@pytest.mark.parametrize(
    ("forward", "backward"),
    [
        (interp.pose_to_dq, interp.dq_to_pose),
        (interp.pose_to_motor, interp.motor_to_pose),
    ],
    ids=["dq", "motor"],
)
def test_pose_round_trips_through_dq_and_motor(forward: object, backward: object) -> None:
    """pose -> dual quaternion / motor -> pose gives the pose back (same quaternion sign)."""
    poses = random_poses(1).reshape(10, 100, 7)
    back = backward(forward(poses))  # type: ignore[operator]
    assert back.shape == poses.shape
    np.testing.assert_allclose(back[..., :3], poses[..., :3], rtol=0, atol=4e-15)
    np.testing.assert_allclose(back[..., 3:], poses[..., 3:], rtol=0, atol=4e-16)


def test_pose_round_trips_through_matrix() -> None:
    """pose -> matrix -> pose gives the pose back, with w >= 0."""
    poses = random_poses(2)
    back = interp.matrix_to_pose(interp.pose_to_matrix(poses))
    np.testing.assert_array_equal(back[:, :3], poses[:, :3])
    assert np.max(rotation_angle(back[:, 3:], poses[:, 3:])) <= 1e-14
    assert np.all(back[:, 3] >= 0.0)


def test_matrix_round_trips_through_pose() -> None:
    """matrix -> pose -> matrix gives the matrix back."""
    m = interp.pose_to_matrix(random_poses(3))
    np.testing.assert_allclose(interp.pose_to_matrix(interp.matrix_to_pose(m)), m, atol=4e-15)


def test_pose_splits_into_tq() -> None:
    """pose_to_tq returns the position and the quaternion parts."""
    poses = random_poses(4)
    t, q = interp.pose_to_tq(poses)
    np.testing.assert_array_equal(t, poses[:, :3])
    np.testing.assert_array_equal(q, poses[:, 3:])


@pytest.mark.parametrize("shape", [(), (5,), (2, 3)])
def test_pose_round_trips_through_tq(shape: tuple[int, ...]) -> None:
    """pose_from_tq(*pose_to_tq(p)) gives p back for any batch shape."""
    # This once raised for every input (it broadcast (..., 1, 3) against (..., 1, 4)).
    poses = random_poses(5, n=int(np.prod(shape))).reshape((*shape, 7))
    np.testing.assert_array_equal(interp.pose_from_tq(*interp.pose_to_tq(poses)), poses)


def test_pose_from_tq_broadcasts_and_validates() -> None:
    """pose_from_tq broadcasts t against q, normalises q and rejects mismatched batches."""
    q = random_poses(25, n=4)[:, 3:]
    poses = interp.pose_from_tq([1.0, 2.0, 3.0], q * 2.0)
    assert poses.shape == (4, 7)
    np.testing.assert_array_equal(poses[:, :3], np.tile([1.0, 2.0, 3.0], (4, 1)))
    np.testing.assert_allclose(poses[:, 3:], q, rtol=0, atol=4e-16)
    with pytest.raises(ValueError, match="matching leading shapes"):
        interp.pose_from_tq(np.zeros((3, 3)), q)
    with pytest.raises(ValueError, match=re.escape("expected `t` to have shape (..., 3)")):
        interp.pose_from_tq(np.zeros((4, 2)), q)


def test_motor_and_dq_are_the_documented_linear_map() -> None:
    """Motor coefficients are (rw, -dx, -dy, -dz, -rz, ry, -rx, -dw) of the dual quaternion."""
    poses = random_poses(6, n=50)
    dq = interp.pose_to_dq(poses)
    rw, rx, ry, rz, dw, dx, dy, dz = dq.T
    expected = np.stack([rw, -dx, -dy, -dz, -rz, ry, -rx, -dw], axis=1)
    np.testing.assert_array_equal(interp.pose_to_motor(poses), expected)


def test_dq_to_pose_normalises_scaled_dual_quaternions() -> None:
    """A dual quaternion scaled by any non-zero factor gives the same pose."""
    poses = random_poses(7, n=200)
    scale = (
        np.random.default_rng(7).uniform(0.1, 10.0, (200, 1))
        * np.where(np.arange(200) % 2 == 0, 1.0, -1.0)[:, None]
    )
    back = interp.dq_to_pose(interp.pose_to_dq(poses) * scale)
    np.testing.assert_allclose(back[:, :3], poses[:, :3], rtol=0, atol=1e-14)
    assert np.max(rotation_angle(back[:, 3:], poses[:, 3:])) <= 1e-15 * 4


# --- quaternion algebra vs scipy ------------------------------------------------


def test_quat_mul_matches_scipy_composition() -> None:
    """quat_mul(p, q) is scipy's ``Rotation(p) * Rotation(q)`` (apply q first)."""
    p, q = random_poses(8)[:, 3:], random_poses(9)[:, 3:]
    ref = wxyz((Rotation.from_quat(xyzw(p)) * Rotation.from_quat(xyzw(q))).as_quat())
    assert np.max(rotation_angle(interp.quat_mul(p, q), ref)) <= 1e-14


def test_quat_mul_is_the_hamilton_product_on_basis_elements() -> None:
    """i j = k, j k = i, k i = j, i^2 = -1 (w first)."""
    one, i, j, k = np.eye(4)
    np.testing.assert_array_equal(interp.quat_mul(i, j), k)
    np.testing.assert_array_equal(interp.quat_mul(j, k), i)
    np.testing.assert_array_equal(interp.quat_mul(k, i), j)
    np.testing.assert_array_equal(interp.quat_mul(i, i), -one)


def test_quat_conj_matches_scipy_inverse() -> None:
    """quat_conj of a unit quaternion is scipy's inverse rotation, and q q* = 1."""
    q = random_poses(10)[:, 3:]
    ref = wxyz(Rotation.from_quat(xyzw(q)).inv().as_quat())
    assert np.max(rotation_angle(interp.quat_conj(q), ref)) <= 1e-15
    ident = interp.quat_mul(q, interp.quat_conj(q))
    np.testing.assert_allclose(ident, np.tile([1.0, 0, 0, 0], (len(q), 1)), atol=4e-16)


def test_quat_conj_does_not_modify_its_input() -> None:
    """quat_conj returns a new array."""
    q = random_poses(11, n=5)[:, 3:]
    before = q.copy()
    interp.quat_conj(q)
    np.testing.assert_array_equal(q, before)


def test_quat_rotate_matches_scipy_apply() -> None:
    """quat_rotate(q, v) equals scipy's ``Rotation(q).apply(v)``, broadcasting over v."""
    q = random_poses(12)[:, 3:]
    v = np.random.default_rng(12).uniform(-5, 5, (len(q), 3))
    ref = Rotation.from_quat(xyzw(q)).apply(v)
    np.testing.assert_allclose(interp.quat_rotate(q, v), ref, rtol=0, atol=1e-14)
    one = np.array([0.0, 0.0, -0.2])
    np.testing.assert_allclose(
        interp.quat_rotate(q, one), Rotation.from_quat(xyzw(q)).apply(one), atol=1e-15
    )


# --- shape errors -----------------------------------------------------------------


@pytest.mark.parametrize("name", METHODS)
def test_interpolators_reject_bad_shape_of_a(name: str) -> None:
    """An ``a`` of shape (3, 6) is refused with the documented wording."""
    f = interp.get(name)
    msg = "expected `a` to have shape (..., 7), got (3, 6)"
    with pytest.raises(ValueError, match=re.escape(msg)):
        f(np.zeros((3, 6)), np.zeros((3, 7)), 0.5)


@pytest.mark.parametrize("name", METHODS)
def test_interpolators_reject_bad_shape_of_b(name: str) -> None:
    """A ``b`` of shape (3, 6) is refused with the documented wording."""
    a = random_poses(13, n=3)
    msg = "expected `b` to have shape (..., 7), got (3, 6)"
    with pytest.raises(ValueError, match=re.escape(msg)):
        interp.get(name)(a, np.zeros((3, 6)), 0.5)


@pytest.mark.parametrize("name", METHODS)
def test_interpolators_reject_scalars_and_mismatched_batches(name: str) -> None:
    """A 0-d ``a``, unbroadcastable ``a``/``b`` and unbroadcastable ``s`` raise ValueError."""
    f = interp.get(name)
    a, b = random_poses(14, n=3), random_poses(15, n=4)
    with pytest.raises(ValueError, match=re.escape("expected `a` to have shape (..., 7), got ()")):
        f(1.0, b, 0.5)
    with pytest.raises(ValueError, match="matching shapes"):
        f(a, b, 0.5)
    with pytest.raises(ValueError, match="broadcastable"):
        f(a, a, np.full(4, 0.5))


@pytest.mark.parametrize(
    "func",
    [interp.pose_to_dq, interp.pose_to_motor, interp.pose_to_matrix, interp.pose_to_tq],
)
def test_conversions_reject_bad_shape(func: object) -> None:
    """Pose conversions refuse a (3, 6) array, naming the shape."""
    with pytest.raises(ValueError, match=re.escape("to have shape (..., 7), got (3, 6)")):
        func(np.zeros((3, 6)))  # type: ignore[operator]


def test_inverse_conversions_reject_bad_shape() -> None:
    """dq_to_pose, motor_to_pose and matrix_to_pose refuse wrong trailing shapes."""
    with pytest.raises(ValueError, match=re.escape("`dq` to have shape (..., 8), got (2, 7)")):
        interp.dq_to_pose(np.zeros((2, 7)))
    with pytest.raises(ValueError, match=re.escape("`motor` to have shape (..., 8), got (2, 7)")):
        interp.motor_to_pose(np.zeros((2, 7)))
    with pytest.raises(ValueError, match=re.escape("(..., 4, 4), got (2, 3, 3)")):
        interp.matrix_to_pose(np.zeros((2, 3, 3)))


def test_non_numeric_input_raises_value_error() -> None:
    """Strings and ragged lists become ValueError, not TypeError."""
    with pytest.raises(ValueError, match="float array"):
        interp.as_pose([["x"] * 7])
    with pytest.raises(ValueError, match="float array"):
        interp.soa([[0.0] * 7, [0.0] * 6], [[0.0] * 7] * 2, 0.5)


# --- non-finite and degenerate quaternions -------------------------------------


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("index", [0, 3, 6])
@pytest.mark.parametrize("name", METHODS)
def test_interpolators_reject_non_finite_poses(name: str, index: int, bad: float) -> None:
    """A NaN or infinite coordinate in ``a`` or ``b`` raises ValueError."""
    f = interp.get(name)
    good = random_poses(16, n=4)
    broken = good.copy()
    broken[2, index] = bad
    with pytest.raises(ValueError, match="expected `a` to hold finite values"):
        f(broken, good, 0.5)
    with pytest.raises(ValueError, match="expected `b` to hold finite values"):
        f(good, broken, 0.5)


@pytest.mark.parametrize("name", METHODS)
def test_interpolators_reject_non_finite_s(name: str) -> None:
    """A NaN or infinite ``s`` raises ValueError."""
    a = random_poses(17, n=2)
    for bad in (np.nan, np.inf):
        with pytest.raises(ValueError, match="`s` to hold finite values"):
            interp.get(name)(a, a, np.array([0.5, bad]))


@pytest.mark.parametrize("name", METHODS)
def test_interpolators_reject_zero_quaternions(name: str) -> None:
    """A zero-norm quaternion in ``a`` or ``b`` raises ValueError."""
    f = interp.get(name)
    good = random_poses(18, n=3)
    broken = good.copy()
    broken[1, 3:] = 0.0
    with pytest.raises(ValueError, match="expected `a` to hold non-zero quaternions"):
        f(broken, good, 0.5)
    with pytest.raises(ValueError, match="expected `b` to hold non-zero quaternions"):
        f(good, broken, 0.5)


def test_as_pose_rejects_non_finite_and_zero_quaternions() -> None:
    """as_pose refuses NaN, infinities and zero quaternions, naming the argument."""
    p = random_poses(19, n=2)
    for bad in (np.nan, np.inf):
        broken = p.copy()
        broken[0, 1] = bad
        with pytest.raises(ValueError, match="expected `keyframes` to hold finite values"):
            interp.as_pose(broken, "keyframes")
    broken = p.copy()
    broken[1, 3:] = 0.0
    with pytest.raises(ValueError, match="non-zero quaternions"):
        interp.as_pose(broken)
    with pytest.raises(ValueError, match="non-zero quaternions"):
        interp.pose_to_dq(broken)


def test_dq_and_motor_readers_reject_degenerate_input() -> None:
    """dq_to_pose / motor_to_pose refuse a zero rotor part and non-finite values."""
    with pytest.raises(ValueError, match="non-zero real part"):
        interp.dq_to_pose(np.zeros(8))
    with pytest.raises(ValueError, match="non-zero real part"):
        interp.motor_to_pose(np.zeros(8))
    with pytest.raises(ValueError, match="finite"):
        interp.dq_to_pose(np.full(8, np.nan))
    with pytest.raises(ValueError, match="finite"):
        interp.matrix_to_pose(np.full((4, 4), np.inf))


@pytest.mark.parametrize("factor", [1.0 + 1e-5, 1.0 - 1e-5, 3.0, 1e-6])
@pytest.mark.parametrize("name", METHODS)
def test_interpolators_normalise_off_unit_quaternions(name: str, factor: float) -> None:
    """Quaternions off unit length by more than 1e-6 are normalised, not rejected."""
    f = interp.get(name)
    a, b = random_poses(20, n=8), random_poses(21, n=8)
    scaled_a, scaled_b = a.copy(), b.copy()
    scaled_a[:, 3:] *= factor
    scaled_b[:, 3:] *= factor
    for s in (0.0, 0.1, 0.5, 1.0):
        got = f(scaled_a, scaled_b, s)
        np.testing.assert_allclose(np.linalg.norm(got[:, 3:], axis=1), 1.0, rtol=0, atol=1e-15)
        want = f(a, b, s)
        np.testing.assert_allclose(got[:, :3], want[:, :3], rtol=0, atol=1e-14)
        assert np.max(rotation_angle(got[:, 3:], want[:, 3:])) <= 1e-14


def test_as_pose_normalises_beyond_tolerance_and_keeps_within() -> None:
    """as_pose normalises a quaternion off by 1e-5 and leaves one off by 1e-7 as is."""
    p = random_poses(22, n=4)
    off = p.copy()
    off[:, 3:] *= 1.0 + 1e-5
    fixed = interp.as_pose(off)
    np.testing.assert_allclose(np.linalg.norm(fixed[:, 3:], axis=1), 1.0, rtol=0, atol=1e-15)
    assert not np.shares_memory(fixed, off)
    np.testing.assert_array_equal(off[:, 3:], p[:, 3:] * (1.0 + 1e-5))  # input untouched
    near = p.copy()
    near[:, 3:] *= 1.0 + 1e-7
    np.testing.assert_array_equal(interp.as_pose(near), near)


@pytest.mark.parametrize("name", METHODS)
@pytest.mark.parametrize(
    "layout",
    # The last three once failed: the transposed rows were a view of the caller's
    # array and the quaternions were normalised in place.
    ["c-order (4, 7)", "single pose (7,)", "one row (1, 7)", "fortran-order (4, 7)"],
)
def test_interpolators_do_not_modify_their_inputs(name: str, layout: str) -> None:
    """Normalising off-unit quaternions never writes into the caller's arrays."""
    p = random_poses(23, n=4)
    p[:, 3:] *= 2.0
    if layout.startswith("single"):
        a, b = p[0].copy(), p[1].copy()
    elif layout.startswith("one row"):
        a, b = p[:1].copy(), p[1:2].copy()
    elif layout.startswith("fortran"):
        a, b = np.asfortranarray(p), np.asfortranarray(p[::-1])
    else:
        a, b = p.copy(), p[::-1].copy()
    a_before, b_before = a.copy(), b.copy()
    interp.get(name)(a, b, 0.5)
    np.testing.assert_array_equal(a, a_before)
    np.testing.assert_array_equal(b, b_before)


@pytest.mark.parametrize("name", METHODS)
def test_interpolators_broadcast_an_off_unit_single_pose(name: str) -> None:
    """A single off-unit pose broadcasts against a batch of one without touching the input."""
    # This once wrote through the np.broadcast_arrays view of `a`.
    p = random_poses(24, n=2)
    a = p[0] * np.array([1, 1, 1, 2, 2, 2, 2.0])
    a_before = a.copy()
    out = interp.get(name)(a, p[1:], 0.25)
    assert out.shape == (1, 7)
    np.testing.assert_array_equal(a, a_before)
