"""The allocation-free row kernels of soa, dq-slerp and motor-lerp against the formulas.

``interp.kernels`` evaluates the three pair interpolators one ufunc at a time
into a per-thread scratch, chunk by chunk (``interp.methods`` wraps them). The
references here are the plain numpy expressions of the formulas in
``interp.methods``' docstrings, as the kernels were written before (fresh
arrays, whole batch at once). soa and motor-lerp must agree with them bit for
bit; dq-slerp, now evaluated in the world frame (no vector rotations), to
float rounding. Also: chunk boundaries change nothing, the row kernels write
into strided outputs, threads do not share scratch, and a call allocates
little beyond its result.
"""

from __future__ import annotations

import itertools
import threading
import tracemalloc

import numpy as np
import pytest
from numpy.typing import NDArray

from posecast import interp
from posecast.interp.kernels import CHUNK, dq_slerp_rows, motor_lerp_rows, share_rows, soa_rows

F64 = NDArray[np.float64]

# --- the formulas, as plain expressions (the kernels' former code) ---------------------


def _prepare(a: F64, b: F64, s: F64) -> tuple[F64, F64, F64]:
    A, B = np.ascontiguousarray(a.T), np.ascontiguousarray(b.T)
    for rows in (A, B):  # quaternions off unit length are normalised, each on its own
        q = rows[3:]
        n2 = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]
        off = np.abs(n2 - 1.0) > 2.0 * 1e-6
        rows[3:, off] /= np.sqrt(n2[off])
    return A, B, np.asarray(s, dtype=np.float64)


def _finish(out: F64, A: F64, B: F64, S: F64) -> F64:
    out[:, S == 0.0] = A[:, S == 0.0]
    out[:, S == 1.0] = B[:, S == 1.0]
    return np.ascontiguousarray(out.T)


def _safe_div(num: F64, den: F64, limit: F64) -> F64:
    out = np.array(limit, dtype=np.float64, copy=True)
    np.divide(num, den, out=out, where=den != 0.0)
    return out


def _align(q0: F64, q1: F64) -> tuple[F64, F64]:
    dot = q0[0] * q1[0] + q0[1] * q1[1] + q0[2] * q1[2] + q0[3] * q1[3]
    sign = interp.methods.hemisphere_sign(q0, q1, dot)
    return q1 * sign, dot * sign


def _sincos(x: F64) -> tuple[F64, F64]:
    if x.size and (x.min() < 0.0 or x.max() > 0.5 * np.pi):
        return np.sin(x), np.cos(x)
    t = np.tan(0.5 * x)
    t2 = t * t
    inv = 1.0 / (1.0 + t2)
    return 2.0 * t * inv, (1.0 - t2) * inv


def _cross(u: F64, v: F64) -> F64:
    return np.stack(
        [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]]
    )


def _qmul(p: F64, q: F64) -> F64:
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ]
    )


def _rotate(q: F64, v: F64, inverse: bool = False) -> F64:
    w, x, y, z = q
    if inverse:
        x, y, z = -x, -y, -z
    xx, yy, zz, xy, xz, yz = x * x, y * y, z * z, x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    vx, vy, vz = v
    return np.stack(
        [
            vx + 2.0 * ((-yy - zz) * vx + (xy - wz) * vy + (xz + wy) * vz),
            vy + 2.0 * ((xy + wz) * vx + (-xx - zz) * vy + (yz - wx) * vz),
            vz + 2.0 * ((xz - wy) * vx + (yz + wx) * vy + (-xx - yy) * vz),
        ]
    )


def ref_soa(a: F64, b: F64, s: F64) -> F64:
    A, B, S = _prepare(a, b, s)
    q0 = A[3:]
    q1, dot = _align(q0, B[3:])
    d, m = q1 - q0, q1 + q0
    nd = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2] + d[3] * d[3])
    nm = np.sqrt(m[0] * m[0] + m[1] * m[1] + m[2] * m[2] + m[3] * m[3])
    sin_w = 0.5 * nd * nm
    sin_sw, cos_sw = _sincos(S * (2.0 * np.arctan2(nd, nm)))
    c0 = _safe_div(sin_w * cos_sw - dot * sin_sw, sin_w, 1.0 - S)
    c1 = _safe_div(sin_sw, sin_w, S)
    out = np.empty_like(A)
    out[:3] = A[:3] + S * (B[:3] - A[:3])
    out[3:] = c0 * q0 + c1 * q1
    return _finish(out, A, B, S)


def ref_dq_slerp(a: F64, b: F64, s: F64) -> F64:
    A, B, S = _prepare(a, b, s)
    t0, q0 = A[:3], A[3:]
    q1, cos_phi = _align(q0, B[3:])
    v = _qmul(q0 * np.array([[1.0], [-1.0], [-1.0], [-1.0]]), q1)[1:]
    sin_phi = np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    sin_s, cos_s = _sincos(S * np.arctan2(sin_phi, cos_phi))
    sin_r = sin_phi * cos_s - cos_phi * sin_s
    cos_r = cos_phi * cos_s + sin_phi * sin_s
    k = _safe_div(sin_s, sin_phi, S)
    kr = _safe_div(sin_r, sin_phi, 1.0 - S)
    kc = k * cos_r
    td = _rotate(q0, B[:3] - t0, inverse=True)
    u = v / np.where(sin_phi > 0.0, sin_phi, 1.0)
    along = (S - kc) * (td[0] * u[0] + td[1] * u[1] + td[2] * u[2])
    t_rel = kc * td + along * u - (k * kr) * _cross(v, td)
    out = np.empty_like(A)
    out[:3] = t0 + _rotate(q0, t_rel)
    out[3:] = _qmul(q0, np.concatenate([cos_s[None], k * v]))
    return _finish(out, A, B, S)


def ref_motor_lerp(a: F64, b: F64, s: F64) -> F64:
    A, B, S = _prepare(a, b, s)
    t0, q0, t1 = A[:3], A[3:], B[:3]
    q1, dot = _align(q0, B[3:])
    r = 1.0 - S
    w0, x0, y0, z0 = q0
    w1, x1, y1, z1 = q1
    cv = np.stack(
        [
            -w0 * x1 + x0 * w1 - y0 * z1 + z0 * y1,
            -w0 * y1 + x0 * z1 + y0 * w1 - z0 * x1,
            -w0 * z1 - x0 * y1 + y0 * x1 + z0 * w1,
        ]
    )
    rr, ss, rs = r * r, S * S, r * S
    num = rr * t0 + ss * t1 + rs * (dot * (t0 + t1) + _cross(t0 - t1, cv))
    out = np.empty_like(A)
    out[:3] = num / (rr + ss + 2.0 * rs * dot)
    qb = r * q0 + S * q1
    out[3:] = qb / np.sqrt(qb[0] * qb[0] + qb[1] * qb[1] + qb[2] * qb[2] + qb[3] * qb[3])
    return _finish(out, A, B, S)


REFERENCES = {"soa": ref_soa, "dq-slerp": ref_dq_slerp, "motor-lerp": ref_motor_lerp}
KERNELS = {"soa": soa_rows, "dq-slerp": dq_slerp_rows, "motor-lerp": motor_lerp_rows}

# --- inputs ------------------------------------------------------------------------


def random_poses(rng: np.random.Generator, n: int) -> F64:
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.concatenate([rng.uniform(-3.0, 3.0, (n, 3)), q], axis=1)


def hard_pairs(n: int, seed: int, extrapolate: bool) -> tuple[F64, F64, F64]:
    """Random pairs with the cases that take other branches, spread over the batch."""
    rng = np.random.default_rng(seed)
    a, b = random_poses(rng, n), random_poses(rng, n)
    s = rng.uniform(0.0, 1.0, n)
    at = rng.permutation(n)
    cut = np.array_split(at, 8)
    b[cut[0]] = a[cut[0]]  # identical keyframes: zero angle, the ratios' limits
    b[cut[1], 3:] = -a[cut[1], 3:]  # same rotation, other sign
    s[cut[2]] = 0.0
    s[cut[3]] = 1.0
    tiny = b[cut[4], 3:] = a[cut[4], 3:] + 1e-9 * rng.normal(size=(len(cut[4]), 4))
    b[cut[4], 3:] = tiny / np.linalg.norm(tiny, axis=1, keepdims=True)
    a[cut[5], 3:] = [1.0, 0.0, 0.0, 0.0]  # exact half turns: the tie rule
    b[cut[5], 3:] = [0.0, 0.0, 1.0, 0.0]
    a[cut[6], 3:] *= 1.0 + 1e-3  # off unit length: renormalised on input
    if extrapolate:
        s[cut[7]] = rng.uniform(-1.0, 2.0, len(cut[7]))
    return a, b, s


CASES = [(1, False), (100, False), (100, True), (CHUNK + 17, False), (5000, False)]


@pytest.mark.parametrize("name", sorted(REFERENCES))
@pytest.mark.parametrize(("n", "extrapolate"), CASES)
def test_kernels_compute_the_formulas(name: str, n: int, extrapolate: bool) -> None:
    """soa and motor-lerp equal the formulas bit for bit; dq-slerp to float rounding."""
    a, b, s = hard_pairs(n, seed=n + extrapolate, extrapolate=extrapolate)
    got = interp.get(name)(a, b, s)
    want = REFERENCES[name](a, b, s)
    assert got.shape == (n, 7) and got.flags.c_contiguous
    if name == "dq-slerp":
        np.testing.assert_allclose(got, want, rtol=0, atol=2e-14)
    else:
        np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("name", sorted(REFERENCES))
def test_chunks_do_not_change_results(name: str) -> None:
    """A batch over several chunks equals its pieces interpolated one call each."""
    a, b, s = hard_pairs(3 * CHUNK + 5, seed=7, extrapolate=False)
    f = interp.get(name)
    whole = f(a, b, s)
    cuts = [0, 1, 700, CHUNK, CHUNK + 1, 2 * CHUNK + 100, 3 * CHUNK + 5]
    parts = [f(a[i:j], b[i:j], s[i:j]) for i, j in itertools.pairwise(cuts)]
    np.testing.assert_array_equal(whole, np.concatenate(parts))


@pytest.mark.parametrize("name", sorted(KERNELS))
def test_row_kernel_writes_strided_output_as_the_method(name: str) -> None:
    """The registry's row kernel on unit rows, into an (M, 7) array's transpose, is f(a, b, s)."""
    a, b, s = hard_pairs(300, seed=3, extrapolate=False)
    a[:, 3:] /= np.linalg.norm(a[:, 3:], axis=1, keepdims=True)
    entry = interp.info(name)
    assert entry.rows is KERNELS[name]
    out = np.full((300, 7), np.nan)
    entry.rows(np.ascontiguousarray(a.T), np.ascontiguousarray(b.T), s, out.T, None, True)
    np.testing.assert_array_equal(out, entry.func(a, b, s))


def test_only_the_three_pair_methods_have_row_kernels() -> None:
    """Window and velocity methods render through their own calls; a row kernel needs a pair."""
    with_rows = {n for n in interp.names() if interp.info(n).rows is not None}
    assert with_rows == set(KERNELS)
    with pytest.raises(ValueError, match="only pair interpolators take a row kernel"):
        interp.register("x-window", interp.motor_cubic, kind="window", rows=soa_rows)


@pytest.mark.parametrize("name", sorted(REFERENCES))
def test_threads_do_not_share_scratch(name: str) -> None:
    """Four threads interpolating different batches at once get their own results."""
    f = interp.get(name)
    inputs = [hard_pairs(CHUNK + 300, seed=k, extrapolate=False) for k in range(4)]
    want = [f(*x) for x in inputs]
    got: list[list[F64]] = [[] for _ in inputs]

    def work(k: int) -> None:
        for _ in range(20):
            got[k].append(f(*inputs[k]))

    threads = [threading.Thread(target=work, args=(k,)) for k in range(len(inputs))]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    for k, results in enumerate(got):
        assert len(results) == 20
        for r in results:
            np.testing.assert_array_equal(r, want[k])


@pytest.mark.parametrize("name", sorted(REFERENCES))
def test_a_call_allocates_little_beyond_its_result(name: str) -> None:
    """At batch 10k the peak of traced memory is the (N, 7) result plus ufunc buffers.

    The former kernels peaked at 7 to 10 times the result (3.8 to 5.5 MB) in
    temporaries; that is what made throughput depend on glibc's allocator
    settings. What remains is numpy's 64 kB iteration buffers of a few
    broadcasting calls.
    """
    f = interp.get(name)
    rng = np.random.default_rng(11)  # the common case: unit poses, s in [0, 1]
    a, b, s = random_poses(rng, 10_000), random_poses(rng, 10_000), rng.uniform(0, 1, 10_000)
    f(a, b, s)  # the thread's scratch exists from here on
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        out = f(a, b, s)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < out.nbytes + 192 * 1024, peak


@pytest.mark.parametrize("products", [False, True])
def test_shared_intermediates_change_nothing(products: bool) -> None:
    """Kernels given share_rows' alignment (and products) give the same bits as alone."""
    a, b, s = hard_pairs(500, seed=9, extrapolate=True)
    a[:, 3:] /= np.linalg.norm(a[:, 3:], axis=1, keepdims=True)
    b[:, 3:] /= np.linalg.norm(b[:, 3:], axis=1, keepdims=True)
    A, B = np.ascontiguousarray(a.T), np.ascontiguousarray(b.T)
    shared = share_rows(A, B, s, products)
    before = [x.copy() for x in (shared.q1, shared.dot, shared.r)]
    for kernel in KERNELS.values():
        alone, with_shared = np.empty((7, 500)), np.empty((7, 500))
        kernel(A, B, s, alone)
        kernel(A, B, s, with_shared, None, False, shared)
        np.testing.assert_array_equal(with_shared, alone, err_msg=kernel.__name__)
    for x, y in zip(before, (shared.q1, shared.dot, shared.r), strict=True):
        np.testing.assert_array_equal(x, y)  # read, never written
