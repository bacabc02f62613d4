"""The optimised motor-cubic, motor-hermite and motor-quintic kernels against plain references.

The kernels in ``interp.cubic`` and ``interp.quintic`` fold the curves into
per-keyframe weights, chunk the batch and sum with ``einsum``. The references
here build every keyframe's unit dual quaternion, its tangents or derivatives
and the Hermite blend term by term, one query at a time where that is clearer,
then normalise by the Study number. On fixed random inputs (sign flips,
non-unit quaternions, missing neighbours, held brackets, ``s`` at and beyond
the ends) both must agree to float rounding.
"""

from __future__ import annotations

import numpy as np
import pytest
from numpy.polynomial import polynomial as P
from numpy.typing import NDArray

from posecast import interp

F64 = NDArray[np.float64]

TOL = 1e-12


# --- plain dual-quaternion algebra, one pose (or a batch) at a time -------------------


def qmul(p: F64, q: F64) -> F64:
    """Hamilton product of quaternions ``(..., 4)``, w first."""
    pw, px, py, pz = np.moveaxis(p, -1, 0)
    qw, qx, qy, qz = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def pure(v: F64) -> F64:
    """Vectors ``(..., 3)`` as pure quaternions."""
    return np.concatenate([np.zeros((*v.shape[:-1], 1)), v], axis=-1)


def conj(q: F64) -> F64:
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def dual_quat(pose: F64) -> F64:
    """Pose ``(..., 7)`` to the unit dual quaternion ``(q, 1/2 (0, t) q)``, ``(..., 8)``."""
    q = pose[..., 3:] / np.linalg.norm(pose[..., 3:], axis=-1, keepdims=True)
    return np.concatenate([q, 0.5 * qmul(pure(pose[..., :3]), q)], axis=-1)


def dq_rate(d: F64, vel: F64) -> F64:
    """Time derivative of unit dual quaternions for world-frame velocities ``(..., 6)``."""
    q, qd = d[..., :4], d[..., 4:]
    t = pure(2.0 * qmul(qd, conj(q))[..., 1:])
    r = 0.5 * qmul(pure(vel[..., 3:]), q)
    return np.concatenate([r, 0.5 * (qmul(pure(vel[..., :3]), q) + qmul(t, r))], axis=-1)


def to_pose(d: F64) -> F64:
    """Blended dual quaternion to the pose of the Study-normalised motor."""
    q, qd = d[..., :4], d[..., 4:]
    n2 = np.sum(q * q, axis=-1, keepdims=True)
    t = 2.0 * qmul(qd, conj(q))[..., 1:] / n2
    return np.concatenate([t, q / np.sqrt(n2)], axis=-1)


def same_side(ref: F64, d: F64) -> F64:
    """``d`` flipped into ``ref``'s hemisphere (random data never ties)."""
    dot = np.sum(ref[..., :4] * d[..., :4], axis=-1, keepdims=True)
    return np.where(dot < 0.0, -d, d)


# --- references --------------------------------------------------------------------


def ref_cubic(keys: F64, times: F64, t: F64) -> F64:
    """Catmull-Rom on motors, one window per row: tangents, Hermite, normalise."""
    d = [dual_quat(keys[:, j]) for j in range(4)]
    d[0] = same_side(d[1], d[0])
    d[2] = same_side(d[1], d[2])
    d[3] = same_side(d[2], d[3])
    t0, t1, t2, t3 = times.T
    out = np.empty((len(t), 7))
    for n in range(len(t)):
        span = t2[n] - t1[n]
        s = 0.0 if span <= 0 else min(max((t[n] - t1[n]) / span, 0.0), 1.0)
        chord = d[2][n] - d[1][n]
        m1 = (d[2][n] - d[0][n]) * span / (t2[n] - t0[n]) if t1[n] > t0[n] else chord
        m2 = (d[3][n] - d[1][n]) * span / (t3[n] - t1[n]) if t3[n] > t2[n] else chord
        h00 = 2 * s**3 - 3 * s**2 + 1
        h10 = s**3 - 2 * s**2 + s
        h01 = -2 * s**3 + 3 * s**2
        h11 = s**3 - s**2
        out[n] = to_pose(h00 * d[1][n] + h10 * m1 + h01 * d[2][n] + h11 * m2)
        if s == 0.0:
            out[n] = keys[n, 1]
        elif s == 1.0:
            out[n] = keys[n, 2]
    return out


def ref_hermite(a: F64, b: F64, va: F64, vb: F64, dt: F64, s: F64) -> F64:
    """Hermite on motors with the reported velocities as tangents."""
    d1 = dual_quat(a)
    d2 = dual_quat(b)
    m1 = dq_rate(d1, va) * dt[:, None]
    m2 = dq_rate(d2, vb) * dt[:, None]
    flip = np.sum(d1[:, :4] * d2[:, :4], axis=1) < 0.0
    d2[flip] *= -1.0
    m2[flip] *= -1.0
    sc = s[:, None]
    h00 = 2 * sc**3 - 3 * sc**2 + 1
    h10 = sc**3 - 2 * sc**2 + sc
    h01 = -2 * sc**3 + 3 * sc**2
    h11 = sc**3 - sc**2
    out = to_pose(h00 * d1 + h10 * m1 + h01 * d2 + h11 * m2)
    out[s == 0.0] = a[s == 0.0]
    out[s == 1.0] = b[s == 1.0]
    return out


def lagrange_derivatives(x: F64, i: int) -> tuple[F64, F64]:
    """First and second derivatives at ``x[i]`` of the Lagrange basis of nodes ``x``."""
    d1, d2 = np.empty(len(x)), np.empty(len(x))
    for j in range(len(x)):
        others = np.delete(x, j)
        basis = P.polyfromroots(others) / np.prod(x[j] - others)
        d1[j] = P.polyval(x[i], P.polyder(basis))
        d2[j] = P.polyval(x[i], P.polyder(basis, 2))
    return d1, d2


def ref_quintic(keys: F64, times: F64, t: F64, lb: int = 2, la: int = 2) -> F64:
    """C2 quintic on motors, one window at a time: polynomial derivatives at both ends.

    The velocity and acceleration at each bracket keyframe are those of the
    polynomial through the keyframes of its stencil that exist (a neighbour
    repeating its inward neighbour's time, and anything beyond it, does not).
    """
    lo, hi = lb, lb + 1
    k = lb + 2 + la
    out = np.empty((len(t), 7))
    for n in range(len(t)):
        tt = times[n]
        span = tt[hi] - tt[lo]
        if span <= 0:
            out[n] = keys[n, lo]
            continue
        s = min(max((t[n] - tt[lo]) / span, 0.0), 1.0)
        x = (tt - tt[lo]) / span
        present = {lo, hi}
        for j in range(hi + 1, k):
            if tt[j] <= tt[j - 1]:
                break
            present.add(j)
        for j in range(lo - 1, -1, -1):
            if tt[j] >= tt[j + 1]:
                break
            present.add(j)
        d = dual_quat(keys[n])
        for j in range(lo + 1, k):
            d[j] = same_side(d[j - 1], d[j])
        for j in range(lo - 1, -1, -1):
            d[j] = same_side(d[j + 1], d[j])
        vel, acc = {}, {}
        for i in (lo, hi):
            nodes = [j for j in sorted(present) if i - lb <= j <= i + la]
            w1, w2 = lagrange_derivatives(x[nodes], nodes.index(i))
            vel[i] = w1 @ d[nodes]
            acc[i] = w2 @ d[nodes]
        h_p1 = 10 * s**3 - 15 * s**4 + 6 * s**5
        h_v0 = s - 6 * s**3 + 8 * s**4 - 3 * s**5
        h_a0 = 0.5 * (s**2 - 3 * s**3 + 3 * s**4 - s**5)
        h_a1 = 0.5 * (s**3 - 2 * s**4 + s**5)
        h_v1 = -4 * s**3 + 7 * s**4 - 3 * s**5
        blend = (
            (1 - h_p1) * d[lo]
            + h_v0 * vel[lo]
            + h_a0 * acc[lo]
            + h_a1 * acc[hi]
            + h_v1 * vel[hi]
            + h_p1 * d[hi]
        )
        out[n] = to_pose(blend)
        if s == 0.0:
            out[n] = keys[n, lo]
        elif s == 1.0:
            out[n] = keys[n, hi]
    return out


# --- fixed random inputs -----------------------------------------------------------


def random_poses(rng: np.random.Generator, shape: tuple[int, ...]) -> F64:
    q = rng.normal(size=(*shape, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return np.concatenate([rng.uniform(-3.0, 3.0, (*shape, 3)), q], axis=-1)


def windows(seed: int, n: int, k: int, lo: int) -> tuple[F64, F64, F64]:
    """Random windows with every edge case the kernels branch on."""
    rng = np.random.default_rng(seed)
    keys = random_poses(rng, (n, k))
    keys[: n // 4, :, 3:] *= -1.0  # whole windows with the other sign
    keys[n // 4 : n // 2, ::2, 3:] *= -1.0  # alternate signs inside the window
    keys[n // 2 : n // 2 + 20, :, 3:] *= 1.25  # off unit length
    times = np.cumsum(rng.uniform(0.03, 0.2, (n, k)), axis=1)
    case = rng.integers(0, 8, n)
    for i in np.flatnonzero(case == 1):  # no neighbour before
        times[i, :lo] = times[i, lo]
        keys[i, :lo] = keys[i, lo]
    for i in np.flatnonzero(case == 2):  # no neighbour after
        times[i, lo + 2 :] = times[i, lo + 1]
        keys[i, lo + 2 :] = keys[i, lo + 1]
    for i in np.flatnonzero(case == 3):  # only the outermost one missing on each side
        times[i, 0] = times[i, 1]
        times[i, -1] = times[i, -2]
    for i in np.flatnonzero(case == 4):  # held bracket
        times[i, lo + 1 :] = times[i, lo]
    if lo > 0 and k > lo + 2:  # the nearest neighbours missing, the outer ones not
        for i in np.flatnonzero(case == 5):
            times[i, lo - 1] = times[i, lo]
            times[i, : lo - 1] -= 0.5
            times[i, lo + 2] = times[i, lo + 1]
            times[i, lo + 3 :] += 0.5
    s = rng.uniform(-0.2, 1.2, n)
    s[::11] = 0.0
    s[3::11] = 1.0
    t = times[:, lo] + s * (times[:, lo + 1] - times[:, lo])
    return keys, times, t


def assert_poses_close(got: F64, want: F64) -> None:
    assert got.shape == want.shape
    assert np.all(np.isfinite(got))
    np.testing.assert_allclose(got[..., :3], want[..., :3], rtol=0, atol=TOL)
    # Same hemisphere by construction (the bracket's lower keyframe decides), so
    # quaternions are compared as they are.
    np.testing.assert_allclose(got[..., 3:], want[..., 3:], rtol=0, atol=TOL)


# --- tests -------------------------------------------------------------------------


@pytest.mark.parametrize("n", [1, 7, 300, 5000])
def test_motor_cubic_matches_reference(n: int) -> None:
    keys, times, t = windows(11 + n, n, 4, 1)
    assert_poses_close(interp.motor_cubic(keys, times, t), ref_cubic(keys, times, t))


@pytest.mark.parametrize("n", [1, 7, 300, 5000])
def test_motor_quintic_matches_reference(n: int) -> None:
    m = min(n, 500)
    keys, times, t = windows(23 + n, m, 6, 2)
    want = ref_quintic(keys, times, t)
    # A batch spanning several kernel chunks: the checked windows, tiled.
    reps = -(-n // m)
    keys, times, t = np.tile(keys, (reps, 1, 1)), np.tile(times, (reps, 1)), np.tile(t, reps)
    got = interp.motor_quintic(keys[:n], times[:n], t[:n])
    assert_poses_close(got, np.tile(want, (reps, 1))[:n])


def test_motor_quintic_each_window_alone_matches_reference() -> None:
    """Windows of one kind per call: nothing borrowed from other windows of the batch."""
    keys, times, t = windows(77, 400, 6, 2)
    kinds = {
        "complete": np.all(np.diff(times, axis=1) > 0, axis=1),
        "inner after missing": (times[:, 3] == times[:, 4]) & (times[:, 5] > times[:, 4]),
        "inner before missing": (times[:, 1] == times[:, 2]) & (times[:, 0] < times[:, 1]),
    }
    for name, rows in kinds.items():
        assert rows.sum() > 5, name
        got = interp.motor_quintic(keys[rows], times[rows], t[rows])
        assert_poses_close(got, ref_quintic(keys[rows], times[rows], t[rows]))
    for i in range(0, 400, 37):
        got = interp.motor_quintic(keys[i], times[i], t[i])
        assert_poses_close(got, ref_quintic(keys[i : i + 1], times[i : i + 1], t[i : i + 1])[0])


@pytest.mark.parametrize(("lb", "la"), [(1, 1), (3, 3), (2, 0), (0, 2), (1, 3)])
def test_window_spline_other_sizes_match_reference(lb: int, la: int) -> None:
    from posecast.interp.quintic import motor_window_spline

    k = lb + 2 + la
    keys, times, t = windows(5 + k, 200, k, lb)
    got = motor_window_spline(keys, times, t, lb, la)
    assert_poses_close(got, ref_quintic(keys, times, t, lb, la))


@pytest.mark.parametrize("n", [1, 9, 5000])
def test_motor_hermite_matches_reference(n: int) -> None:
    rng = np.random.default_rng(31 + n)
    a, b = random_poses(rng, (n,)), random_poses(rng, (n,))
    b[::3, 3:] *= -1.0
    a[1::5, 3:] *= 0.8  # off unit length
    va = np.concatenate([rng.uniform(-5, 5, (n, 3)), rng.uniform(-20, 20, (n, 3))], axis=1)
    vb = np.concatenate([rng.uniform(-5, 5, (n, 3)), rng.uniform(-20, 20, (n, 3))], axis=1)
    dt = rng.uniform(0.03, 0.2, n)
    s = rng.uniform(0.0, 1.0, n)
    s[::13] = 0.0
    s[4::13] = 1.0
    got = interp.motor_hermite(a, b, va, vb, dt, s)
    assert_poses_close(got, ref_hermite(a, b, va, vb, dt, s))


def test_references_see_the_edge_cases() -> None:
    """The fixed inputs do reach the branches (else the comparisons above prove less)."""
    keys, times, t = windows(23 + 300, 300, 6, 2)
    span = times[:, 3] - times[:, 2]
    assert np.any(span == 0) and np.any(times[:, 0] == times[:, 1])
    assert np.any(times[:, 5] == times[:, 4]) and np.any(times[:, 3] == times[:, 4])
    assert np.any((times[:, 3] == times[:, 4]) & (times[:, 5] > times[:, 4]))
    assert np.any((times[:, 1] == times[:, 2]) & (times[:, 0] < times[:, 1]))
    s = (t - times[:, 2]) / np.where(span > 0, span, 1.0)
    assert np.any(s < 0) and np.any(s > 1) and np.any(s == 0) and np.any(s == 1)
    dots = np.sum(keys[:, :-1, 3:] * keys[:, 1:, 3:], axis=-1)
    assert np.any(dots < 0)
