"""Interpolators over more than two keyframes, and velocity-aware ones.

The paper's methods see only the two keyframes that bracket a query. These
use more information while keeping the rigid-motion algebra:

- ``motor-cubic``: a cubic Hermite curve through the motors (dual quaternions)
  with Catmull-Rom tangents from the neighbouring keyframes (non-uniform times:
  ``m_k = (M_{k+1} - M_{k-1}) / (t_{k+1} - t_{k-1})``), then Study-number
  normalisation. Blending motors linearly commutes with a change of world frame,
  so the curve is frame-invariant; position and rotation stay coupled. The
  tangents are shared by the two segments meeting at a keyframe, so pose and
  velocity are continuous across keyframes. It needs the keyframe after the
  bracket: one more interval of playout delay.
- ``motor-hermite``: the same curve with tangents from the linear and angular
  velocities the tracker reported with each keyframe (no look-ahead).
- :func:`screw_extrapolate`: dead reckoning along the last screw motion (the
  ScLERP of the two newest keyframes continued past ``s = 1``), with a bounded
  horizon.

A window is four keyframes ``P (..., 4, 7)`` at times ``T (..., 4)`` around a
query ``t`` in ``[T1, T2]``. A missing neighbour is given as a copy of its
bracket keyframe with the same time (``T0 == T1`` or ``T3 == T2``); the tangent
then falls back to the one-sided difference.
"""

from __future__ import annotations

import itertools

import numpy as np
from numpy.typing import ArrayLike

from posecast.interp.kernels import SCRATCH_ROWS, scratch
from posecast.interp.methods import _rows, dq_slerp, hemisphere_sign
from posecast.interp.pose import F64, UNIT_TOLERANCE

__all__ = [
    "VELOCITY_SIZE",
    "motor_cubic",
    "motor_hermite",
    "screw_extrapolate",
]

#: A velocity is 6 numbers: linear (m/s) then angular (rad/s), both in the world frame.
VELOCITY_SIZE = 6


def _checked(x: ArrayLike, name: str, tail: tuple[int, ...]) -> F64:
    arr = _float_array(x, name, tail)
    # One reduction first: a non-finite sum is rare, then we look closer.
    if not np.isfinite(arr.sum()) and not np.all(np.isfinite(arr)):
        raise ValueError(f"expected `{name}` to hold finite values")
    return arr


def _float_array(x: ArrayLike, name: str, tail: tuple[int, ...]) -> F64:
    """``x`` as a float64 array ending in ``tail`` (finiteness is checked later, on rows)."""
    try:
        arr = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"expected `{name}` to be a float array: {exc}") from None
    if arr.ndim < len(tail) or arr.shape[arr.ndim - len(tail) :] != tail:
        shape = "(..., " + ", ".join(str(d) for d in tail) + ")"
        raise ValueError(f"expected `{name}` to have shape {shape}, got {arr.shape}")
    return arr


def _window_rows(p: F64) -> F64:
    """Windows ``(M, K, 7)`` as a contiguous ``(7, K, M)`` array of component rows, in
    this thread's scratch (:func:`interp.kernels.scratch`: valid until its next use).

    Each component of all keyframes is one contiguous ``(K, M)`` block, so the
    element-wise work runs over contiguous memory (about twice as fast as over
    strided rows here). Finite values and non-zero quaternions are checked, and
    the quaternions normalised in place when any is off unit length.
    """
    m, k = p.shape[0], p.shape[1]
    if 7 * k <= SCRATCH_ROWS:  # no fresh (7, K, M) block per chunk: glibc would mmap it
        rows = scratch(m)[0][: 7 * k].reshape(7, k, m)
        np.copyto(rows, p.transpose(2, 1, 0))  # fast on a chunk of queries
    else:
        rows = np.ascontiguousarray(p.transpose(2, 1, 0))
    q = rows[3:]
    n2 = np.einsum("ckm,ckm->km", q, q)
    lo, hi = n2.min(), n2.max()
    # |q|^2 is finite exactly when q is; one sum covers the positions.
    finite = np.isfinite(hi) and np.isfinite(rows[:3].sum())
    if not finite and not np.all(np.isfinite(rows)):
        raise ValueError("expected `keys` to hold finite values")
    if not lo > 1e-24:
        raise ValueError("expected poses to hold non-zero quaternions")
    if hi - 1.0 > 2.0 * UNIT_TOLERANCE or 1.0 - lo > 2.0 * UNIT_TOLERANCE:
        q /= np.sqrt(n2)
    return rows


def _chain_signs(coef: F64, real: F64, lo: int) -> None:
    """Flip the weights ``coef (K, M)`` of keyframes outside their inward neighbour's hemisphere.

    ``real (4, K, M)`` are the quaternions. Keyframe ``j > lo`` is put in the
    hemisphere of ``j - 1`` (after that one's own flip), ``j < lo`` in that of
    ``j + 1``: a motor's sign is a factor of its weight. Exact half turns (dot 0)
    are decided by ``hemisphere_sign``'s rule.
    """
    dots = np.einsum("ckm,ckm->km", real[:, :-1], real[:, 1:])  # (K - 1, M): j with j + 1
    fwd = np.copysign(1.0, dots)  # aligns j + 1 to j
    back = fwd  # aligns j to j + 1
    if not dots.all():  # a zero dot: an exact half turn somewhere
        ties = np.flatnonzero(~dots.all(axis=1))
        back = fwd.copy()
        for tie in ties:
            fwd[tie] = hemisphere_sign(real[:, tie], real[:, tie + 1], dots[tie])
            back[tie] = hemisphere_sign(real[:, tie + 1], real[:, tie], dots[tie])
    k = coef.shape[0]
    if lo + 1 < k:
        sign = fwd[lo]
        coef[lo + 1] *= sign
        for j in range(lo + 2, k):
            sign = sign * fwd[j - 1]
            coef[j] *= sign
    if lo > 0:
        sign = back[lo - 1]
        coef[lo - 1] *= sign
        for j in range(lo - 2, -1, -1):
            sign = sign * back[j]
            coef[j] *= sign


def _blend(rows: F64, coef: F64, real: F64, dual: F64) -> None:
    """``sum_j coef_j M_j`` of the windows' motors into ``real`` and ``dual`` (twice the dual part).

    With ``M_j = q_j + e 1/2 (0, t_j) q_j``, twice the dual part of the blend is
    ``sum_j coef_j (0, t_j) q_j``: from the 12 sums ``sum_j coef_j t_j q_j^T``
    (one ``einsum`` pass, no temporaries). Each query only sums its own keyframes.
    """
    q = rows[3:]
    np.einsum("km,ckm->cm", coef, q, out=real)
    tq = np.einsum("km,ikm,jkm->ijm", coef, rows[:3], q)  # (3, 4, M): t_i q_j
    # (0, t) q = (-t.v, w t + t x v), with v the vector part of q
    np.add(tq[0, 1], tq[1, 2], out=dual[0])
    dual[0] += tq[2, 3]
    np.negative(dual[0], out=dual[0])
    np.add(tq[0, 0], tq[1, 3], out=dual[1])
    dual[1] -= tq[2, 2]
    np.add(tq[1, 0], tq[2, 1], out=dual[2])
    dual[2] -= tq[0, 3]
    np.add(tq[2, 0], tq[0, 2], out=dual[3])
    dual[3] -= tq[1, 1]


def _pose_rows(real: F64, dual2: F64) -> F64:
    """Pose rows ``(7, M)`` of a blended motor (real part, twice the dual part).

    Dividing by the Study number: rotation ``qr / |qr|``, translation
    ``vec(2 qd qr*) / |qr|^2`` (the Study number's dual part only changes the
    scalar part, which is never formed).
    """
    w, x, y, z = real
    dw, dx, dy, dz = dual2
    m = real.shape[1]
    inv = w * w
    tmp = np.empty(m)
    for c in (x, y, z):
        np.multiply(c, c, out=tmp)
        inv += tmp
    np.divide(1.0, inv, out=inv)
    out = np.empty((7, m))
    for row, terms in (
        (out[0], ((dx, w, 1), (dw, x, -1), (dy, z, -1), (dz, y, 1))),
        (out[1], ((dy, w, 1), (dw, y, -1), (dx, z, 1), (dz, x, -1))),
        (out[2], ((dz, w, 1), (dw, z, -1), (dx, y, -1), (dy, x, 1))),
    ):
        (a0, b0, _), *rest = terms
        np.multiply(a0, b0, out=row)
        for a1, b1, sg in rest:
            np.multiply(a1, b1, out=tmp)
            if sg > 0:
                row += tmp
            else:
                row -= tmp
        row *= inv
    np.sqrt(inv, out=inv)
    np.multiply(real, inv, out=out[3:])
    return out


#: Queries per chunk of the window kernels (a few hundred kB of temporaries).
CHUNK = 2048


def _window_curve(flat: F64, coef: F64, lo: int) -> F64:
    """Poses ``(M, 7)`` of the normalised blends ``sum_j coef_j M_j`` of windows ``(M, K, 7)``.

    ``coef (K, M)`` are the keyframes' weights for the motors as given; they are
    flipped in place where a keyframe's sign is chained into its inward
    neighbour's hemisphere, outwards from keyframe ``lo``. The motors are
    processed in chunks of queries: the transpose is several times faster on a
    chunk, and every temporary stays in the core's caches. Each query only
    involves its own keyframes, so the result does not depend on the chunks.
    """
    m = flat.shape[0]
    if m == 1:  # two copies: keeps einsum's sums off its contiguous (reordered) path
        return _window_curve(np.concatenate([flat, flat]), coef.repeat(2, axis=1), lo)[:1]
    real = np.empty((4, m))
    dual = np.empty((4, m))
    bounds = [*range(0, m, CHUNK), m]
    if len(bounds) > 2 and m - bounds[-2] == 1:
        del bounds[-2]  # no chunk of one query (see above)
    for c0, c1 in itertools.pairwise(bounds):
        rows = _window_rows(flat[c0:c1])
        w = coef[:, c0:c1]
        _chain_signs(w, rows[3:], lo)
        _blend(rows, w, real[:, c0:c1], dual[:, c0:c1])
    return np.ascontiguousarray(_pose_rows(real, dual).T)


def motor_cubic(keys: ArrayLike, times: ArrayLike, t: ArrayLike) -> F64:
    """Catmull-Rom cubic on motors through a window of 4 keyframes, at times ``t``.

    The Hermite curve ``h00 M1 + h10 m1 + h01 M2 + h11 m2`` with tangents that
    are differences of the window's motors is a weighted sum of the four motors;
    the weights depend on ``s`` and the times only, so the motors themselves
    are blended once (:func:`_window_curve`).
    """
    p = _float_array(keys, "keys", (4, 7))
    tt = _checked(times, "times", (4,))
    batch = p.shape[:-2]
    if tt.shape[:-1] != batch:
        tt = np.broadcast_to(tt, (*batch, 4))
    q = np.broadcast_to(_checked(t, "t", ()), batch).reshape(-1).astype(np.float64)
    flat, times2 = p.reshape(-1, 4, 7), tt.reshape(-1, 4)
    m = q.shape[0]
    if m <= _CUBIC_CHUNK:
        return _cubic_rows(flat, times2, q).reshape((*batch, 7))
    # Chunks of queries keep the temporaries to a few hundred kB that glibc keeps
    # in its heap, so the throughput does not depend on how the process tuned its
    # allocator (batch 10k: 6.9 M/s either way; unchunked 3.1 plain, 7.1 tuned).
    out = np.empty((m, 7))
    for c0 in range(0, m, _CUBIC_CHUNK):
        c1 = min(m, c0 + _CUBIC_CHUNK)
        out[c0:c1] = _cubic_rows(flat[c0:c1], times2[c0:c1], q[c0:c1])
    return out.reshape((*batch, 7))


#: Queries per chunk of :func:`motor_cubic` (measured: 1024 and 2048 pay more
#: per-call overhead, an unchunked 10k batch depends on the allocator).
_CUBIC_CHUNK = 4096


def _cubic_rows(flat: F64, tt: F64, q: F64) -> F64:
    """:func:`motor_cubic` on windows ``(M, 4, 7)``, times ``(M, 4)``, queries ``(M,)``."""
    T = _rows(tt)
    t0, t1, t2, t3 = T
    span = t2 - t1
    if not (np.all(span >= 0) and np.all(t1 >= t0) and np.all(t3 >= t2)):
        raise ValueError("expected window times with T0 <= T1 <= T2 <= T3")
    live = span > 0
    # T1 == T2 is a held keyframe: s = 0 reproduces it.
    s = np.where(live, np.clip((q - t1) / np.where(live, span, 1.0), 0.0, 1.0), 0.0)
    h00, h10, h01, h11 = _hermite_basis(s)
    # Tangents (in spans): m1 = a (M2 - M0), or the chord M2 - M1 without M0;
    # m2 = b (M3 - M1), or the chord without M3.
    w0 = t2 - t0
    w3 = t3 - t1
    has0 = t1 > t0
    has3 = t3 > t2
    a = np.where(has0, span / np.where(w0 > 0, w0, 1.0), 0.0)
    b = np.where(has3, span / np.where(w3 > 0, w3, 1.0), 0.0)
    coef = np.empty((4, q.shape[0]))
    np.multiply(h10, a, out=coef[0])
    np.negative(coef[0], out=coef[0])
    np.multiply(h11, b, out=coef[3])
    g10 = np.where(has0, 0.0, h10)  # chord part of m1
    g11 = np.where(has3, 0.0, h11)  # chord part of m2
    # M1: h00 - (chord of m1) - h11 (b or 1); M2: h01 + h10 (a or 1) + (chord of m2)
    coef[1] = h00 - g10 - coef[3] - g11
    coef[2] = h01 - coef[0] + g10 + g11
    out = _window_curve(flat, coef, 1)
    for mask, j in ((s == 0.0, 1), (s == 1.0, 2)):
        if mask.any():
            out[mask] = flat[mask, j]
    return out


def _hermite_basis(s: F64) -> tuple[F64, F64, F64, F64]:
    """Cubic Hermite basis ``h00, h10, h01, h11`` (unit interval)."""
    s2 = s * s
    s3 = s2 * s
    h01 = 3.0 * s2 - 2.0 * s3
    h00 = 1.0 - h01
    h11 = s3 - s2
    h10 = h11 - s2 + s
    return h00, h10, h01, h11


def _unit_quats(rows: F64, name: str) -> F64:
    """Pose rows ``(7, M)`` with finite values and unit quaternions (a copy if normalised)."""
    q = rows[3:]
    n2 = np.einsum("cm,cm->m", q, q)
    lo, hi = n2.min(initial=1.0), n2.max(initial=1.0)
    # |q|^2 is finite exactly when q is; one sum covers the positions.
    finite = np.isfinite(hi) and np.isfinite(rows[:3].sum())
    if not finite and not np.all(np.isfinite(rows)):
        raise ValueError(f"expected `{name}` to hold finite values")
    if not lo > 1e-24:
        raise ValueError("expected poses to hold non-zero quaternions")
    if hi - 1.0 > 2.0 * UNIT_TOLERANCE or 1.0 - lo > 2.0 * UNIT_TOLERANCE:
        rows = rows.copy()
        rows[3:] /= np.sqrt(n2)
    return rows


def _finite_rows(x: F64, name: str) -> F64:
    """``_rows(x)``, checked for finite values with one reduction."""
    rows = _rows(x)
    if not np.isfinite(rows.sum()) and not np.all(np.isfinite(rows)):
        raise ValueError(f"expected `{name}` to hold finite values")
    return rows


def _sum_products(out: F64, terms: tuple[tuple[F64, F64, bool], ...], tmp: F64, add: bool) -> None:
    """``out (+)= sum(+-a * b)`` over ``terms`` of ``(a, b, negative)``, in place."""
    for n, (a, b, negative) in enumerate(terms):
        if n == 0 and not add and not negative:
            np.multiply(a, b, out=out)
            continue
        np.multiply(a, b, out=tmp)
        if n == 0 and not add:
            np.negative(tmp, out=out)
        elif negative:
            out -= tmp
        else:
            out += tmp


def _hermite_end(rows: F64, vel: F64, g: F64, c: F64, real: F64, dual: F64, add: bool) -> None:
    """One keyframe's share of the motor Hermite curve, into ``real`` and ``dual`` (times 2).

    The keyframe's motor ``M = q + e 1/2 (0, t) q`` enters with weight ``g`` and
    its time derivative ``M' = 1/2 (0, a) q + e 1/2 ((0, v) q + (0, t) 1/2 (0, a) q)``
    (world-frame velocities ``v``, ``a``) with weight ``c``. Both real parts
    together are ``Q = (g + (0, c a / 2)) q``, and twice both dual parts
    ``(0, t) Q + (0, c v) q``. ``add``: accumulate instead of overwrite.
    """
    tx, ty, tz, w, x, y, z = rows
    k = 0.5 * c
    ux, uy, uz = vel[3:] * k
    ex, ey, ez = vel[:3] * c
    tmp = np.empty_like(g)
    q = np.empty((4, g.shape[0]))
    qw, qx, qy, qz = q
    _sum_products(qw, ((g, w, False), (ux, x, True), (uy, y, True), (uz, z, True)), tmp, False)
    _sum_products(qx, ((g, x, False), (ux, w, False), (uy, z, False), (uz, y, True)), tmp, False)
    _sum_products(qy, ((g, y, False), (uy, w, False), (uz, x, False), (ux, z, True)), tmp, False)
    _sum_products(qz, ((g, z, False), (uz, w, False), (ux, y, False), (uy, x, True)), tmp, False)
    if add:
        real += q
    else:
        real[...] = q
    dw, dx, dy, dz = dual
    t, e, r, qv = (tx, ty, tz), (ex, ey, ez), (x, y, z), (qx, qy, qz)
    # Scalar part: -(t . Q) - (e . q).
    _sum_products(dw, tuple((a, b, True) for a, b in zip(t + e, qv + r, strict=True)), tmp, add)
    for i, d in enumerate((dx, dy, dz)):
        # Vector part of (0, t) Q + (0, e) q, the same terms cycled through (x, y, z).
        j, m = (i + 1) % 3, (i + 2) % 3
        terms = (
            (t[i], qw, False),
            (t[j], qv[m], False),
            (t[m], qv[j], True),
            (e[i], w, False),
            (e[j], r[m], False),
            (e[m], r[j], True),
        )
        _sum_products(d, terms, tmp, add)


def motor_hermite(
    a: ArrayLike,
    b: ArrayLike,
    va: ArrayLike,
    vb: ArrayLike,
    dt: ArrayLike,
    s: ArrayLike,
) -> F64:
    """Hermite curve on motors between ``a`` and ``b`` with reported velocities.

    ``va``, ``vb`` are ``(..., 6)`` world-frame velocities (linear m/s, then
    angular rad/s) at the keyframes, ``dt`` the time between them (s) and ``s``
    the fraction in ``[0, 1]``. With zero velocities and the tangents of a
    constant-speed path it reduces to a smooth ease; with the true velocities of
    a constant screw it follows the screw to third order.

    The curve ``h00 M_a + h10 dt M_a' + h01 M_b + h11 dt M_b'`` (``M_b`` and its
    derivative in ``M_a``'s hemisphere) is formed directly as one real and one
    dual quaternion per query, then normalised by its Study number.
    """
    batch, span, ss, rows_a, rows_b, A, B, vel_a, vel_b = _hermite_inputs(a, b, va, vb, dt, s)
    qa, qb = A[3:], B[3:]
    dot = qa[0] * qb[0] + qa[1] * qb[1] + qa[2] * qb[2] + qa[3] * qb[3]
    # The derivative of -M is -M': b's sign is a factor of both its weights.
    sign = hemisphere_sign(qa, qb, dot)
    h00, h10, h01, h11 = _hermite_basis(ss)
    real = np.empty((4, ss.shape[0]))
    dual = np.empty((4, ss.shape[0]))
    _hermite_end(A, vel_a, h00, h10 * span, real, dual, False)
    _hermite_end(B, vel_b, h01 * sign, h11 * (span * sign), real, dual, True)
    out = _pose_rows(real, dual)
    return _exact_ends(out, ss, rows_a, rows_b, batch)


def _hermite_inputs(
    a: ArrayLike, b: ArrayLike, va: ArrayLike, vb: ArrayLike, dt: ArrayLike, s: ArrayLike
) -> tuple[tuple[int, ...], F64, F64, F64, F64, F64, F64, F64, F64]:
    """The checked, broadcast inputs of a velocity method (motor- and soa-hermite).

    Returns the batch shape, ``dt`` and ``s`` flattened, the keyframes as rows
    ``(7, M)``, their unit-quaternion checked copies ``A``, ``B`` and the finite
    velocities as rows ``(6, M)``.
    """
    pa = _float_array(a, "a", (7,))
    pb = _float_array(b, "b", (7,))
    if pa.shape != pb.shape:
        pa, pb = np.broadcast_arrays(pa, pb)
    batch = pa.shape[:-1]
    vva = np.broadcast_to(_float_array(va, "va", (VELOCITY_SIZE,)), (*batch, VELOCITY_SIZE))
    vvb = np.broadcast_to(_float_array(vb, "vb", (VELOCITY_SIZE,)), (*batch, VELOCITY_SIZE))
    span = np.broadcast_to(_checked(dt, "dt", ()), batch).reshape(-1)
    if not np.all(span > 0):
        raise ValueError("expected `dt` to be positive")
    ss = np.broadcast_to(_checked(s, "s", ()), batch).reshape(-1).astype(np.float64)
    rows_a, rows_b = _rows(pa), _rows(pb)
    A = _unit_quats(rows_a, "a")
    B = _unit_quats(rows_b, "b")
    vel_a, vel_b = _finite_rows(vva, "va"), _finite_rows(vvb, "vb")
    return batch, span, ss, rows_a, rows_b, A, B, vel_a, vel_b


def _exact_ends(out: F64, ss: F64, rows_a: F64, rows_b: F64, batch: tuple[int, ...]) -> F64:
    """Rows ``(7, M)`` as poses ``(*batch, 7)``, the keyframes themselves at s = 0 and 1."""
    for mask, src in ((ss == 0.0, rows_a), (ss == 1.0, rows_b)):
        if mask.any():
            out[:, mask] = src[:, mask]
    return np.ascontiguousarray(out.T).reshape((*batch, 7))


def screw_extrapolate(a: ArrayLike, b: ArrayLike, s: ArrayLike, max_s: float = 2.0) -> F64:
    """Continue the screw motion from ``a`` to ``b`` to fraction ``s >= 1``.

    ``s`` is clipped to ``[0, max_s]``: a bounded horizon, so a lost stream
    drifts at most ``max_s - 1`` keyframe intervals past its newest keyframe.
    """
    return dq_slerp(a, b, np.clip(np.asarray(s, dtype=np.float64), 0.0, max_s))
