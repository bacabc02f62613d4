"""The interpolators and pose conversions against independent libraries.

References: scipy ``Rotation``/``Slerp`` (scalar-last) for SoA, pytransform3d's
dual-quaternion ScLERP and scipy ``RigidTransform`` exponential coordinates for
ScLERP, kingdon 3D PGA motors (``Algebra(3, 0, 1)``, ``.normalized()``) for
motor LERP. Poses are compared, not raw coefficients: positions to 1e-12 of the
translation scale ``max(1, |t0|, |t1|)`` and rotations to 1e-12 rad with a
sign-insensitive angle.

pytransform3d's per-pose functions cost about half a millisecond a call, so they
run on a 300-pair subset (interior s) plus every edge case (all s); its vectorised
``pytransform3d.trajectories`` twins, scipy and kingdon run on all 10,000 pairs.
"""

from __future__ import annotations

from collections.abc import Callable
from types import ModuleType
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from posecast import interp

F64 = NDArray[np.float64]
Reference = Callable[[F64, F64, float], F64]

N_RANDOM = 10_000
N_PER_POSE = 300
N_EDGE = 16
S_VALUES = (0.0, 0.1, 0.5, 0.9, 1.0)
TOL = 1e-12
EDGE_CASES = (
    "identical",
    "rel-1e-9",
    "rel-1e-7",
    "rel-1e-5",
    "neg-rel-1e-9",
    "neg-rel-1e-7",
    "neg-rel-1e-5",
    "rel-179deg",
    "neg-rel-179deg",
    "pure-translation",
    "neg-pure-translation",
)

# --- helpers ----------------------------------------------------------------


def random_poses(rng: np.random.Generator, n: int, extent: float = 3.0) -> F64:
    """Positions uniform in a cube of half-side ``extent`` m, uniform unit quaternions."""
    t = rng.uniform(-extent, extent, (n, 3))
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.concatenate([t, q], axis=1)


def axis_angle_quat(rng: np.random.Generator, n: int, angle: float) -> F64:
    """Quaternions (w first) rotating by ``angle`` rad about random axes."""
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    half = 0.5 * angle
    return np.concatenate([np.full((n, 1), np.cos(half)), np.sin(half) * axis], axis=1)


def edge_case(name: str, n: int = N_EDGE) -> tuple[F64, F64]:
    """Pose pairs ``(a, b)`` for one named edge case (seeded by the name)."""
    rng = np.random.default_rng(sum(name.encode()))
    a = random_poses(rng, n)
    b = random_poses(rng, n)
    base = name.removeprefix("neg-")
    if base == "identical":
        b = a.copy()
    elif base.startswith("rel-"):
        angle = np.radians(179.0) if base == "rel-179deg" else float(base.removeprefix("rel-"))
        b[:, 3:] = interp.quat_mul(a[:, 3:], axis_angle_quat(rng, n, angle))
    elif base == "pure-translation":
        b[:, 3:] = a[:, 3:]
    else:
        raise AssertionError(name)
    if name.startswith("neg-"):
        b[:, 3:] *= -1.0
    return a, b


def rotation_angle(q0: F64, q1: F64) -> F64:
    """Angle in rad between unit quaternion rotations, blind to their sign."""
    q1 = q1 * np.where(np.sum(q0 * q1, axis=-1) < 0.0, -1.0, 1.0)[..., None]
    # |q1 - q0| = 2 sin(angle/4): accurate for tiny angles, unlike acos.
    d = np.linalg.norm(q1 - q0, axis=-1)
    m = np.linalg.norm(q1 + q0, axis=-1)
    out: F64 = 4.0 * np.arctan2(d, m)
    return out


def assert_poses_agree(got: F64, ref: F64, a: F64, b: F64, what: str) -> None:
    """Positions within 1e-12 of the translation scale, rotations within 1e-12 rad."""
    scale = np.maximum(
        1.0, np.maximum(np.linalg.norm(a[..., :3], axis=-1), np.linalg.norm(b[..., :3], axis=-1))
    )
    dp = np.linalg.norm(got[..., :3] - ref[..., :3], axis=-1) / scale
    dq = rotation_angle(got[..., 3:], ref[..., 3:])
    worst_p, worst_q = int(np.argmax(dp)), int(np.argmax(dq))
    assert dp[worst_p] <= TOL, f"{what}: position off by {dp[worst_p]:.3g} at pair {worst_p}"
    assert dq[worst_q] <= TOL, f"{what}: rotation off by {dq[worst_q]:.3g} rad at pair {worst_q}"


def xyzw(q: F64) -> F64:
    """w-first quaternions to scipy's scalar-last order."""
    return q[..., [1, 2, 3, 0]]


def wxyz(q: F64) -> F64:
    """scipy's scalar-last quaternions to w first."""
    return q[..., [3, 0, 1, 2]]


# --- fixtures and references ------------------------------------------------


@pytest.fixture(scope="module")
def random_pairs() -> tuple[F64, F64]:
    """10,000 seeded random pose pairs, positions within 3 m per axis."""
    rng = np.random.default_rng(20240607)
    return random_poses(rng, N_RANDOM), random_poses(rng, N_RANDOM)


@pytest.fixture(scope="module")
def spatial() -> ModuleType:
    """``scipy.spatial.transform``."""
    module: ModuleType = pytest.importorskip("scipy.spatial.transform")
    return module


@pytest.fixture(scope="module")
def rigid_transform(spatial: ModuleType) -> Any:
    """scipy's ``RigidTransform`` class (scipy >= 1.16)."""
    rt = getattr(spatial, "RigidTransform", None)
    if rt is None:
        pytest.skip("the installed scipy has no RigidTransform (needs scipy >= 1.16)")
    return rt


@pytest.fixture(scope="module")
def pt() -> ModuleType:
    """``pytransform3d.transformations`` (per-pose API)."""
    module: ModuleType = pytest.importorskip("pytransform3d.transformations")
    return module


@pytest.fixture(scope="module")
def ptr() -> ModuleType:
    """``pytransform3d.trajectories`` (vectorised API)."""
    module: ModuleType = pytest.importorskip("pytransform3d.trajectories")
    return module


@pytest.fixture(scope="module")
def pga() -> Any:
    """kingdon's 3D projective geometric algebra ``Algebra(3, 0, 1)``."""
    kingdon = pytest.importorskip("kingdon")
    return kingdon.Algebra(3, 0, 1)


def scipy_soa(spatial: ModuleType) -> Reference:
    """SoA from scipy: numpy position LERP, ``r0 exp(s log(r0^-1 r1))`` rotation.

    This is what ``Slerp`` computes between two keyframes, vectorised over pairs
    (one ``Slerp`` per pair is checked separately on a subset).
    """
    rotation = spatial.Rotation

    def ref(a: F64, b: F64, s: float) -> F64:
        r0 = rotation.from_quat(xyzw(a[:, 3:]))
        r1 = rotation.from_quat(xyzw(b[:, 3:]))
        rs = r0 * rotation.from_rotvec(s * (r0.inv() * r1).as_rotvec())
        t = a[:, :3] + s * (b[:, :3] - a[:, :3])
        return np.concatenate([t, wxyz(rs.as_quat())], axis=1)

    return ref


def scipy_slerp_pairs(spatial: ModuleType, a: F64, b: F64) -> F64:
    """One scipy ``Slerp`` per pair, evaluated at every s: ``(len(S_VALUES), n, 7)``."""
    out = np.empty((len(S_VALUES), len(a), 7))
    s = np.array(S_VALUES)
    for i, (pa, pb) in enumerate(zip(a, b, strict=True)):
        key = spatial.Rotation.from_quat(xyzw(np.stack([pa[3:], pb[3:]])))
        out[:, i, 3:] = wxyz(spatial.Slerp([0.0, 1.0], key)(s).as_quat())
        out[:, i, :3] = pa[:3] + s[:, None] * (pb[:3] - pa[:3])
    return out


def scipy_screw(spatial: ModuleType, rigid_transform: Any) -> Reference:
    """ScLERP from scipy: ``A * RigidTransform.from_exp_coords(s * log(A^-1 B))``."""

    def ref(a: F64, b: F64, s: float) -> F64:
        ta = rigid_transform.from_components(a[:, :3], spatial.Rotation.from_quat(xyzw(a[:, 3:])))
        tb = rigid_transform.from_components(b[:, :3], spatial.Rotation.from_quat(xyzw(b[:, 3:])))
        x = ta * rigid_transform.from_exp_coords(s * (ta.inv() * tb).as_exp_coords())
        return np.concatenate([x.translation, wxyz(x.rotation.as_quat())], axis=1)

    return ref


def pt_dual_quats(pt: ModuleType, a: F64, b: F64) -> tuple[F64, F64]:
    """pytransform3d dual quaternions of ``a`` and ``b``, ``b`` in ``a``'s hemisphere.

    pytransform3d's ScLERP does not pick the short way itself.
    """
    dqa = np.array([pt.dual_quaternion_from_pq(p) for p in a])
    dqb = np.array([pt.dual_quaternion_from_pq(p) for p in b])
    dqb[np.sum(dqa[:, :4] * dqb[:, :4], axis=1) < 0.0] *= -1.0
    return dqa, dqb


def pt_sclerp(pt: ModuleType) -> Reference:
    """ScLERP from pytransform3d's per-pose ``dual_quaternion_sclerp``."""

    def ref(a: F64, b: F64, s: float) -> F64:
        dqa, dqb = pt_dual_quats(pt, a, b)
        return np.array(
            [
                pt.pq_from_dual_quaternion(pt.dual_quaternion_sclerp(x, y, s))
                for x, y in zip(dqa, dqb, strict=True)
            ]
        )

    return ref


def ptr_sclerp(ptr: ModuleType) -> Reference:
    """ScLERP from pytransform3d's vectorised ``dual_quaternions_sclerp``."""

    def ref(a: F64, b: F64, s: float) -> F64:
        dqa = ptr.dual_quaternions_from_pqs(a)
        dqb = ptr.dual_quaternions_from_pqs(b)
        dqb[np.sum(dqa[:, :4] * dqb[:, :4], axis=1) < 0.0] *= -1.0
        out: F64 = ptr.pqs_from_dual_quaternions(
            ptr.dual_quaternions_sclerp(dqa, dqb, np.full(len(a), s))
        )
        return out

    return ref


def coefficient(mv: Any, blade: str, n: int) -> F64:
    """One coefficient of an array-valued kingdon multivector, as an ``(n,)`` array."""
    return np.broadcast_to(np.asarray(getattr(mv, blade), dtype=np.float64), (n,))


def kingdon_motor(pga: Any, poses: F64) -> Any:
    """The paper's motors ``M = T R``: ``T = 1 - 1/2 e0 t``, ``R = w - x e23 + y e13 - z e12``."""
    t, q = poses[:, :3].T, poses[:, 3:].T
    translator = 1.0 - 0.5 * pga.blades.e0 * pga.vector(e1=t[0], e2=t[1], e3=t[2])
    rotor = pga.multivector(e=q[0], e23=-q[1], e13=q[2], e12=-q[3])
    return translator * rotor


def kingdon_pose(pga: Any, motor: Any, n: int) -> F64:
    """Pose of a normalised kingdon motor: ``q`` from its rotor part, ``t`` from ``M R~``."""
    w, e12, e13, e23 = (coefficient(motor, k, n) for k in ("e", "e12", "e13", "e23"))
    rotor = pga.multivector(e=w, e12=e12, e13=e13, e23=e23)
    translator = motor * ~rotor
    t = -2.0 * np.stack([coefficient(translator, k, n) for k in ("e01", "e02", "e03")], axis=1)
    return np.concatenate([t, np.stack([w, -e23, e13, -e12], axis=1)], axis=1)


def kingdon_motor_lerp(pga: Any) -> Reference:
    """Motor LERP in kingdon: ``((1-s) M0 + s M1).normalized()``, M1 in M0's hemisphere."""

    def ref(a: F64, b: F64, s: float) -> F64:
        n = len(a)
        m0, m1 = kingdon_motor(pga, a), kingdon_motor(pga, b)
        dot = sum(coefficient(m0, k, n) * coefficient(m1, k, n) for k in ("e", "e12", "e13", "e23"))
        m1 = pga.scalar(e=np.where(dot < 0.0, -1.0, 1.0)) * m1
        return kingdon_pose(pga, ((1.0 - s) * m0 + s * m1).normalized(), n)

    return ref


# --- SoA ----------------------------------------------------------------------


@pytest.mark.parametrize("s", S_VALUES)
def test_soa_matches_scipy_on_random_pairs(
    spatial: ModuleType, random_pairs: tuple[F64, F64], s: float
) -> None:
    """SoA equals numpy LERP + scipy rotation SLERP on 10,000 random pairs."""
    a, b = random_pairs
    assert_poses_agree(interp.soa(a, b, s), scipy_soa(spatial)(a, b, s), a, b, f"soa s={s}")


@pytest.mark.parametrize("case", EDGE_CASES)
def test_soa_matches_scipy_on_edge_cases(spatial: ModuleType, case: str) -> None:
    """SoA equals the scipy reference on tiny, flipped, large and zero rotations."""
    a, b = edge_case(case)
    for s in S_VALUES:
        assert_poses_agree(interp.soa(a, b, s), scipy_soa(spatial)(a, b, s), a, b, f"{case} {s}")


@pytest.mark.parametrize("case", ("random", *EDGE_CASES))
def test_soa_matches_scipy_slerp_objects(spatial: ModuleType, case: str) -> None:
    """SoA equals one scipy ``Slerp`` per keyframe pair (random subset and edge cases)."""
    if case == "random":
        rng = np.random.default_rng(7)
        a, b = random_poses(rng, 200), random_poses(rng, 200)
    else:
        a, b = edge_case(case)
    ref = scipy_slerp_pairs(spatial, a, b)
    for i, s in enumerate(S_VALUES):
        assert_poses_agree(interp.soa(a, b, s), ref[i], a, b, f"{case} s={s}")


# --- dual-quaternion ScLERP ------------------------------------------------


@pytest.mark.parametrize("s", S_VALUES)
def test_dq_slerp_matches_scipy_exp_coords_on_random_pairs(
    spatial: ModuleType, rigid_transform: Any, random_pairs: tuple[F64, F64], s: float
) -> None:
    """ScLERP equals scipy's ``A exp(s log(A^-1 B))`` on 10,000 random pairs."""
    a, b = random_pairs
    ref = scipy_screw(spatial, rigid_transform)(a, b, s)
    assert_poses_agree(interp.dq_slerp(a, b, s), ref, a, b, f"dq-slerp s={s}")


@pytest.mark.parametrize("case", EDGE_CASES)
def test_dq_slerp_matches_scipy_exp_coords_on_edge_cases(
    spatial: ModuleType, rigid_transform: Any, case: str
) -> None:
    """ScLERP equals scipy's exp-coordinate screw on the edge cases."""
    a, b = edge_case(case)
    ref = scipy_screw(spatial, rigid_transform)
    for s in S_VALUES:
        assert_poses_agree(interp.dq_slerp(a, b, s), ref(a, b, s), a, b, f"{case} s={s}")


@pytest.mark.parametrize("s", S_VALUES)
def test_dq_slerp_matches_pytransform3d_batch_on_random_pairs(
    ptr: ModuleType, random_pairs: tuple[F64, F64], s: float
) -> None:
    """ScLERP equals pytransform3d's vectorised ``dual_quaternions_sclerp`` on 10,000 pairs."""
    a, b = random_pairs
    assert_poses_agree(interp.dq_slerp(a, b, s), ptr_sclerp(ptr)(a, b, s), a, b, f"s={s}")


def test_dq_slerp_matches_pytransform3d_per_pose(pt: ModuleType) -> None:
    """ScLERP equals pytransform3d's per-pose ``dual_quaternion_sclerp`` on 300 pairs."""
    rng = np.random.default_rng(11)
    a, b = random_poses(rng, N_PER_POSE), random_poses(rng, N_PER_POSE)
    for s in (0.1, 0.5, 0.9):  # the endpoints are covered by the vectorised twin
        assert_poses_agree(interp.dq_slerp(a, b, s), pt_sclerp(pt)(a, b, s), a, b, f"s={s}")


@pytest.mark.parametrize("case", EDGE_CASES)
def test_dq_slerp_matches_pytransform3d_on_edge_cases(
    pt: ModuleType, ptr: ModuleType, case: str
) -> None:
    """ScLERP equals both pytransform3d ScLERP functions on the edge cases."""
    a, b = edge_case(case)
    for s in S_VALUES:
        got = interp.dq_slerp(a, b, s)
        assert_poses_agree(got, pt_sclerp(pt)(a, b, s), a, b, f"{case} per-pose s={s}")
        assert_poses_agree(got, ptr_sclerp(ptr)(a, b, s), a, b, f"{case} batch s={s}")


# --- motor LERP ---------------------------------------------------------------


@pytest.mark.parametrize("s", S_VALUES)
def test_motor_lerp_matches_kingdon_on_random_pairs(
    pga: Any, random_pairs: tuple[F64, F64], s: float
) -> None:
    """Motor LERP equals kingdon's normalised motor blend on 10,000 random pairs."""
    a, b = random_pairs
    ref = kingdon_motor_lerp(pga)(a, b, s)
    assert_poses_agree(interp.motor_lerp(a, b, s), ref, a, b, f"motor-lerp s={s}")


@pytest.mark.parametrize("case", EDGE_CASES)
def test_motor_lerp_matches_kingdon_on_edge_cases(pga: Any, case: str) -> None:
    """Motor LERP equals kingdon's normalised motor blend on the edge cases."""
    a, b = edge_case(case)
    for s in S_VALUES:
        ref = kingdon_motor_lerp(pga)(a, b, s)
        assert_poses_agree(interp.motor_lerp(a, b, s), ref, a, b, f"{case} s={s}")


# --- conversions --------------------------------------------------------------


def test_pose_to_motor_matches_kingdon_coefficients(
    pga: Any, random_pairs: tuple[F64, F64]
) -> None:
    """pose_to_motor is kingdon's ``T R`` as (1, e01, e02, e03, e12, e13, e23, e0123)."""
    a = random_pairs[0]
    motor = kingdon_motor(pga, a)
    blades = ("e", "e01", "e02", "e03", "e12", "e13", "e23", "e0123")
    ref = np.stack([coefficient(motor, k, len(a)) for k in blades], axis=1)
    np.testing.assert_allclose(interp.pose_to_motor(a), ref, rtol=0, atol=1e-15)


def test_motor_to_pose_matches_kingdon_normalisation(pga: Any) -> None:
    """motor_to_pose of arbitrary even multivectors equals kingdon's ``.normalized()`` pose."""
    rng = np.random.default_rng(5)
    n = 2000
    coeffs = rng.normal(size=(8, n))  # not rigid: scaled, with a stray e0123 part
    ref = kingdon_pose(pga, pga.evenmv(coeffs).normalized(), n)
    got = interp.motor_to_pose(coeffs.T)
    scale = np.maximum(1.0, np.linalg.norm(ref[:, :3], axis=1))
    assert np.max(np.linalg.norm(got[:, :3] - ref[:, :3], axis=1) / scale) <= 1e-12
    assert np.max(rotation_angle(got[:, 3:], ref[:, 3:])) <= 1e-12


def test_pose_to_dq_matches_pytransform3d(
    pt: ModuleType, ptr: ModuleType, random_pairs: tuple[F64, F64]
) -> None:
    """pose_to_dq equals pytransform3d's ``dual_quaternion_from_pq`` (same order, same sign)."""
    a = random_pairs[0]
    np.testing.assert_allclose(
        interp.pose_to_dq(a), ptr.dual_quaternions_from_pqs(a), rtol=0, atol=1e-15
    )
    for p in a[:N_PER_POSE]:
        np.testing.assert_allclose(
            interp.pose_to_dq(p), pt.dual_quaternion_from_pq(p), rtol=0, atol=1e-15
        )


def test_dq_to_pose_matches_pytransform3d(pt: ModuleType, random_pairs: tuple[F64, F64]) -> None:
    """dq_to_pose equals pytransform3d's ``pq_from_dual_quaternion``."""
    b = random_pairs[1]
    dqs = np.array([pt.dual_quaternion_from_pq(p) for p in b[:N_PER_POSE]])
    ref = np.array([pt.pq_from_dual_quaternion(d) for d in dqs])
    got = interp.dq_to_pose(dqs)
    assert_poses_agree(got, ref, b[:N_PER_POSE], b[:N_PER_POSE], "dq_to_pose")


def test_pose_to_matrix_matches_scipy(spatial: ModuleType, random_pairs: tuple[F64, F64]) -> None:
    """pose_to_matrix has scipy's rotation matrix and the translation in the last column."""
    a = random_pairs[0]
    m = interp.pose_to_matrix(a)
    rot = spatial.Rotation.from_quat(xyzw(a[:, 3:])).as_matrix()
    np.testing.assert_allclose(m[:, :3, :3], rot, rtol=0, atol=4e-15)  # a few ulp
    np.testing.assert_array_equal(m[:, :3, 3], a[:, :3])
    np.testing.assert_array_equal(m[:, 3, :], np.tile([0.0, 0.0, 0.0, 1.0], (len(a), 1)))


def test_matrix_to_pose_matches_scipy(spatial: ModuleType, random_pairs: tuple[F64, F64]) -> None:
    """matrix_to_pose equals scipy's ``Rotation.from_matrix``, half-turns included."""
    rng = np.random.default_rng(3)
    half_turns = axis_angle_quat(rng, 200, np.pi)  # w = 0: the trace-based branch fails here
    quats = np.concatenate([random_pairs[0][:, 3:], half_turns])
    t = rng.uniform(-3.0, 3.0, (len(quats), 3))
    m = np.zeros((len(quats), 4, 4))
    m[:, :3, :3] = spatial.Rotation.from_quat(xyzw(quats)).as_matrix()
    m[:, :3, 3] = t
    m[:, 3, 3] = 1.0
    got = interp.matrix_to_pose(m)
    ref_q = wxyz(spatial.Rotation.from_matrix(m[:, :3, :3]).as_quat())
    np.testing.assert_array_equal(got[:, :3], t)
    assert np.max(rotation_angle(got[:, 3:], ref_q)) <= 1e-12
    assert np.max(np.abs(np.linalg.norm(got[:, 3:], axis=1) - 1.0)) <= 1e-15
    assert np.all(got[:, 3] >= 0.0)
