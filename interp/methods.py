"""The paper's three two-keyframe interpolators, vectorised over ``(..., 7)``.

All three share one contract: ``f(a, b, s)`` with poses ``a``, ``b`` of shape
``(..., 7)`` and ``s`` broadcastable to ``a.shape[:-1]``; the result is
``(..., 7)`` float64 with unit quaternions, exactly ``a`` at ``s = 0`` and
exactly ``b`` at ``s = 1``. Each puts ``b``'s quaternion in ``a``'s hemisphere
first, so ``q`` and ``-q`` interpolate identically.

- ``soa``: position LERP + quaternion SLERP (what engines do today).
- ``dq_slerp``: dual-quaternion screw interpolation (ScLERP), i.e. the SE(3)
  geodesic ``A exp(s log(A^-1 B))``, written in closed form on the screw.
- ``motor_lerp``: linear blend of PGA motors then Study-number normalisation,
  written in closed form on (t, q): its rotation is the normalised quaternion
  LERP and its translation the one of the normalised blended motor.

Every ``sin(x)/sin(y)`` ratio is taken directly (both sines are accurate to an ulp
at any angle) with its limit substituted only at an exactly zero angle, so tiny
rotations are as exact as large ones, without branches.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from interp.pose import F64, UNIT_TOLERANCE

__all__ = ["dq_slerp", "motor_lerp", "prepare", "soa"]


def _check_pose_array(x: ArrayLike, name: str) -> F64:
    try:
        arr = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"expected `{name}` to be a float array: {exc}") from None
    if arr.ndim == 0 or arr.shape[-1] != 7:
        raise ValueError(f"expected `{name}` to have shape (..., 7), got {arr.shape}")
    return arr


def _rows(x: F64) -> F64:
    """``(..., n)`` to a contiguous ``(n, M)`` array of component rows.

    The kernels work component-major so that every numpy operation runs over
    contiguous memory (markedly faster than strided columns of ``(N, 7)``).
    """
    return np.ascontiguousarray(x.reshape(-1, x.shape[-1]).T)


def _validate_rows(rows: F64, name: str) -> F64:
    """Check finiteness and quaternion norms of pose rows; normalise a copy if needed.

    ``rows`` may be a view of the caller's array (when the transpose is already
    contiguous), so it is never written to.
    """
    # One reduction first: a non-finite sum is rare, then we look closer.
    if not np.isfinite(rows.sum()) and not np.all(np.isfinite(rows)):
        raise ValueError(f"expected `{name}` to hold finite values")
    q = rows[3:]
    n2 = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]
    # |q|^2 - 1 ~ 2 (|q| - 1): compare squared norms to twice the tolerance.
    if np.any(np.abs(n2 - 1.0) > 2.0 * UNIT_TOLERANCE):
        if not np.all(n2 > 1e-24):
            raise ValueError(f"expected `{name}` to hold non-zero quaternions")
        rows = rows.copy()
        rows[3:] /= np.sqrt(n2)
    return rows


def prepare(a: ArrayLike, b: ArrayLike, s: ArrayLike) -> tuple[F64, F64, F64, tuple[int, ...]]:
    """Validate the arguments of an interpolator and lay them out as rows.

    Returns pose rows ``A``, ``B`` of shape ``(7, M)`` (unit quaternions), ``S``
    of shape ``(M,)``, and the batch shape ``a.shape[:-1]`` after broadcasting.
    """
    a_arr = _check_pose_array(a, "a")
    b_arr = _check_pose_array(b, "b")
    if a_arr.shape != b_arr.shape:
        try:
            a_arr, b_arr = np.broadcast_arrays(a_arr, b_arr)
        except ValueError:
            raise ValueError(
                f"expected `a` and `b` to have matching shapes (..., 7), "
                f"got {a_arr.shape} and {b_arr.shape}"
            ) from None
    batch = a_arr.shape[:-1]
    s_arr = np.asarray(s, dtype=np.float64)
    if not np.all(np.isfinite(s_arr)):
        raise ValueError("expected `s` to hold finite values")
    try:
        s_b = np.broadcast_to(s_arr, batch)
    except ValueError:
        raise ValueError(
            f"expected `s` to be broadcastable to {batch}, got {s_arr.shape}"
        ) from None
    A = _validate_rows(_rows(a_arr), "a")
    B = _validate_rows(_rows(b_arr), "b")
    return A, B, s_b.reshape(-1), batch


def _finish(out: F64, A: F64, B: F64, S: F64, batch: tuple[int, ...]) -> F64:
    """Rows back to ``(..., 7)``; s = 0 and s = 1 give the keyframes bit for bit."""
    at0 = S == 0.0
    if at0.any():
        out[:, at0] = A[:, at0]
    at1 = S == 1.0
    if at1.any():
        out[:, at1] = B[:, at1]
    return np.ascontiguousarray(out.T).reshape((*batch, 7))


def _safe_div(num: F64, den: F64, limit: F64) -> F64:
    """``num / den``, or ``limit`` where ``den == 0`` (a zero angle's limit)."""
    out = np.array(limit, dtype=np.float64, copy=True)
    np.divide(num, den, out=out, where=den != 0.0)
    return out


def hemisphere_sign(q0: F64, q1: F64, dot: F64) -> F64:
    """+1 or -1 per row: the sign that puts ``q1`` in ``q0``'s hemisphere.

    At an exact half turn (``q0.q1 == 0``) both ways round are equally short;
    the sign of the zero would decide, so negating an input would flip the
    path. There the relative rotation ``q0* q1`` (a pure vector) is chosen with
    its largest component positive: a rule about rotations, not about signs.
    """
    sign: F64 = np.copysign(1.0, dot)
    ties = dot == 0.0
    if ties.any():
        a, b = q0[:, ties], q1[:, ties]
        # Vector part of q0* q1.
        rel = np.stack(
            [
                a[0] * b[1] - a[1] * b[0] - a[2] * b[3] + a[3] * b[2],
                a[0] * b[2] + a[1] * b[3] - a[2] * b[0] - a[3] * b[1],
                a[0] * b[3] - a[1] * b[2] + a[2] * b[1] - a[3] * b[0],
            ]
        )
        pick = np.take_along_axis(rel, np.argmax(np.abs(rel), axis=0)[None], axis=0)[0]
        sign[ties] = np.where(pick < 0.0, -1.0, 1.0)
    return sign


def _align(q0: F64, q1: F64) -> tuple[F64, F64]:
    """``q1`` rows moved into ``q0``'s hemisphere, and ``q0.q1 >= 0`` after it."""
    dot = q0[0] * q1[0] + q0[1] * q1[1] + q0[2] * q1[2] + q0[3] * q1[3]
    sign = hemisphere_sign(q0, q1, dot)
    return q1 * sign, dot * sign


# The helpers write rows into one preallocated array: np.stack of freshly
# computed rows costs more than the arithmetic itself at these sizes.


def _cross(u: F64, v: F64) -> F64:
    out = np.empty((3, u.shape[-1]))
    np.subtract(u[1] * v[2], u[2] * v[1], out=out[0])
    np.subtract(u[2] * v[0], u[0] * v[2], out=out[1])
    np.subtract(u[0] * v[1], u[1] * v[0], out=out[2])
    return out


def _qmul(p: F64, q: F64) -> F64:
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    out = np.empty((4, p.shape[-1]))
    out[0] = pw * qw - px * qx - py * qy - pz * qz
    out[1] = pw * qx + px * qw + py * qz - pz * qy
    out[2] = pw * qy - px * qz + py * qw + pz * qx
    out[3] = pw * qz + px * qy - py * qx + pz * qw
    return out


def _rotate(q: F64, v: F64, inverse: bool = False) -> F64:
    """Rotate vector rows ``v (3, M)`` by quaternion rows ``q (4, M)`` (or by q*).

    Through the rotation matrix's 9 coefficients: fewer passes than the two
    cross products of ``v + 2 w (u x v) + 2 u x (u x v)``.
    """
    w, x, y, z = q
    if inverse:
        x, y, z = -x, -y, -z
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    vx, vy, vz = v
    out = np.empty((3, v.shape[-1]))
    out[0] = vx + 2.0 * ((-yy - zz) * vx + (xy - wz) * vy + (xz + wy) * vz)
    out[1] = vy + 2.0 * ((xy + wz) * vx + (-xx - zz) * vy + (yz - wx) * vz)
    out[2] = vz + 2.0 * ((xz - wy) * vx + (yz + wx) * vy + (-xx - yy) * vz)
    return out


def _sincos(x: F64) -> tuple[F64, F64]:
    """sin and cos of angles in ``[0, pi/2]`` through ``t = tan(x/2)``.

    This numpy's float64 sin and cos are scalar loops while tan is vectorised;
    with ``t <= 1`` the half-angle forms are accurate to an ulp. Outside that
    range (extrapolation) the plain functions are used.
    """
    if x.size and (x.min() < 0.0 or x.max() > 0.5 * np.pi):
        return np.sin(x), np.cos(x)
    t = np.tan(0.5 * x)
    t2 = t * t
    inv = 1.0 / (1.0 + t2)
    return 2.0 * t * inv, (1.0 - t2) * inv


def soa(a: ArrayLike, b: ArrayLike, s: ArrayLike) -> F64:
    """Position LERP + shortest-path quaternion SLERP."""
    A, B, S, batch = prepare(a, b, s)
    q0 = A[3:]
    q1, dot = _align(q0, B[3:])
    # Angle between q0 and q1 from the half chords |q1 -+ q0| = 2 sin, 2 cos(w/2):
    # accurate near 0, unlike acos(dot); and sin(w) = |d| |m| / 2 without trig.
    d = q1 - q0
    m = q1 + q0
    nd = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2] + d[3] * d[3])
    nm = np.sqrt(m[0] * m[0] + m[1] * m[1] + m[2] * m[2] + m[3] * m[3])
    sin_w = 0.5 * nd * nm
    sw = S * (2.0 * np.arctan2(nd, nm))
    sin_sw, cos_sw = _sincos(sw)
    # sin((1-s) w) = sin w cos sw - cos w sin sw; the limits at w = 0 are 1-s and s.
    r = 1.0 - S
    c0 = _safe_div(sin_w * cos_sw - dot * sin_sw, sin_w, r)
    c1 = _safe_div(sin_sw, sin_w, S)
    out = np.empty_like(A)
    out[:3] = A[:3] + S * (B[:3] - A[:3])
    out[3:] = c0 * q0 + c1 * q1
    return _finish(out, A, B, S, batch)


def dq_slerp(a: ArrayLike, b: ArrayLike, s: ArrayLike) -> F64:
    """Dual-quaternion ScLERP: constant-speed screw motion from ``a`` to ``b``.

    With the relative motion ``q_d = q0* q1 = (cos phi, sin phi u)`` and
    ``t_d = R0^T (t1 - t0)``, the screw at fraction s rotates by ``2 s phi``
    about ``u`` and advances ``s (t_d.u) u`` along it, while the perpendicular
    part ``t_perp`` moves on the circle about the screw axis:
    ``sin(s phi)/sin(phi) Rot(u, -(1-s) phi) t_perp``.
    """
    A, B, S, batch = prepare(a, b, s)
    t0, q0 = A[:3], A[3:]
    q1, cos_phi = _align(q0, B[3:])
    qd = _qmul(q0 * np.array([[1.0], [-1.0], [-1.0], [-1.0]]), q1)
    v = qd[1:]
    sin_phi = np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    sphi = S * np.arctan2(sin_phi, cos_phi)  # phi in [0, pi/2]: cos_phi >= 0
    sin_s, cos_s = _sincos(sphi)
    # (1-s) phi by angle addition: no further trig calls.
    sin_r = sin_phi * cos_s - cos_phi * sin_s
    cos_r = cos_phi * cos_s + sin_phi * sin_s
    r = 1.0 - S
    k = _safe_div(sin_s, sin_phi, S)  # sin(s phi) / sin(phi)
    kr = _safe_div(sin_r, sin_phi, r)  # sin((1-s) phi) / sin(phi)
    kc = k * cos_r
    td = _rotate(q0, B[:3] - t0, inverse=True)
    # Unit axis, or 0 without rotation (the along-axis term then has weight 0).
    u = v / np.where(sin_phi > 0.0, sin_phi, 1.0)
    along = (S - kc) * (td[0] * u[0] + td[1] * u[1] + td[2] * u[2])
    t_rel = kc * td + along * u - (k * kr) * _cross(v, td)
    q_rel = np.concatenate([cos_s[None], k * v])
    out = np.empty_like(A)
    out[:3] = t0 + _rotate(q0, t_rel)
    out[3:] = _qmul(q0, q_rel)
    return _finish(out, A, B, S, batch)


def motor_lerp(a: ArrayLike, b: ArrayLike, s: ArrayLike) -> F64:
    """Motor LERP: blend ``(1-s) M0 + s M1`` and divide by its Study number.

    In (t, q) form, with ``c = q0 q1*`` (``c_w = q0.q1 >= 0`` after alignment),
    the normalised blend has rotation ``nlerp(q0, q1, s)`` and translation

        [(1-s)^2 t0 + s^2 t1 + s(1-s) (c_w (t0 + t1) + (t0 - t1) x c_v)]
        / [(1-s)^2 + s^2 + 2 s (1-s) c_w]

    The Study number's dual part only changes the scalar part of ``2 qd qr*``,
    which this form never computes, so the result is the properly normalised
    motor's pose (dividing by ``sqrt(S)`` alone would leave a non-rigid motor).
    """
    A, B, S, batch = prepare(a, b, s)
    t0, q0, t1 = A[:3], A[3:], B[:3]
    q1, dot = _align(q0, B[3:])
    r = 1.0 - S
    w0, x0, y0, z0 = q0
    w1, x1, y1, z1 = q1
    # Vector part of c = q0 q1*.
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
    return _finish(out, A, B, S, batch)
