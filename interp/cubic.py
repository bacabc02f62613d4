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

import numpy as np
from numpy.typing import ArrayLike

from interp.methods import _rows, dq_slerp, hemisphere_sign
from interp.pose import F64, UNIT_TOLERANCE

__all__ = [
    "VELOCITY_SIZE",
    "motor_cubic",
    "motor_hermite",
    "screw_extrapolate",
]

#: A velocity is 6 numbers: linear (m/s) then angular (rad/s), both in the world frame.
VELOCITY_SIZE = 6


def _checked(x: ArrayLike, name: str, tail: tuple[int, ...]) -> F64:
    try:
        arr = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"expected `{name}` to be a float array: {exc}") from None
    if arr.ndim < len(tail) or arr.shape[arr.ndim - len(tail) :] != tail:
        shape = "(..., " + ", ".join(str(d) for d in tail) + ")"
        raise ValueError(f"expected `{name}` to have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"expected `{name}` to hold finite values")
    return arr


def _dq_rows(rows: F64) -> F64:
    """Pose rows (7, M) to unit dual-quaternion rows (8, M); quaternions normalised."""
    q = rows[3:]
    n2 = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]
    if not np.all(n2 > 1e-24):
        raise ValueError("expected poses to hold non-zero quaternions")
    if np.any(np.abs(n2 - 1.0) > 2.0 * UNIT_TOLERANCE):
        q = q / np.sqrt(n2)
    w, x, y, z = q
    tx, ty, tz = rows[0], rows[1], rows[2]
    # qd = 1/2 (0, t) q
    return np.stack(
        [
            w,
            x,
            y,
            z,
            0.5 * (-tx * x - ty * y - tz * z),
            0.5 * (tx * w + ty * z - tz * y),
            0.5 * (-tx * z + ty * w + tz * x),
            0.5 * (tx * y - ty * x + tz * w),
        ]
    )


def _align_to(ref: F64, d: F64) -> tuple[F64, F64]:
    """``d`` (8, M) flipped into ``ref``'s hemisphere; also the sign used."""
    dot = ref[0] * d[0] + ref[1] * d[1] + ref[2] * d[2] + ref[3] * d[3]
    sign = hemisphere_sign(ref[:4], d[:4], dot)
    return d * sign, sign


def _dq_to_pose_rows(b: F64) -> F64:
    """Blended (unnormalised) dual-quaternion rows to pose rows (7, M).

    Dividing by the Study number: the rotation is ``qr/|qr|`` and the
    translation ``vec(2 qd qr*) / |qr|^2`` (the dual part of the Study number
    only affects the scalar part, which is never formed).
    """
    w, x, y, z, dw, dx, dy, dz = b
    n2 = w * w + x * x + y * y + z * z
    inv = 1.0 / n2
    out = np.empty((7, b.shape[1]))
    # 2 qd qr*, vector part
    out[0] = 2.0 * (-dw * x + dx * w - dy * z + dz * y) * inv
    out[1] = 2.0 * (-dw * y + dx * z + dy * w - dz * x) * inv
    out[2] = 2.0 * (-dw * z - dx * y + dy * x + dz * w) * inv
    r = np.sqrt(inv)
    out[3], out[4], out[5], out[6] = w * r, x * r, y * r, z * r
    return out


def _hermite(d1: F64, d2: F64, m1: F64, m2: F64, s: F64) -> F64:
    s2 = s * s
    s3 = s2 * s
    h00 = 2.0 * s3 - 3.0 * s2 + 1.0
    h10 = s3 - 2.0 * s2 + s
    h01 = 3.0 * s2 - 2.0 * s3
    h11 = s3 - s2
    out: F64 = h00 * d1 + h10 * m1 + h01 * d2 + h11 * m2
    return out


def _finish(rows: F64, batch: tuple[int, ...], s: F64, p1: F64, p2: F64) -> F64:
    out = np.ascontiguousarray(rows.T).reshape((*batch, 7))
    flat = out.reshape(-1, 7)
    for mask, src in ((s == 0.0, p1), (s == 1.0, p2)):
        if mask.any():
            flat[mask] = src.reshape(-1, 7)[mask]
    return out


def motor_cubic(keys: ArrayLike, times: ArrayLike, t: ArrayLike) -> F64:
    """Catmull-Rom cubic on motors through a window of 4 keyframes, at times ``t``."""
    p = _checked(keys, "keys", (4, 7))
    tt = _checked(times, "times", (4,))
    batch = p.shape[:-2]
    if tt.shape[:-1] != batch:
        tt = np.broadcast_to(tt, (*batch, 4))
    q = np.broadcast_to(_checked(t, "t", ()), batch).reshape(-1).astype(np.float64)
    T = _rows(tt)
    t0, t1, t2, t3 = T
    span = t2 - t1
    if not (np.all(span >= 0) and np.all(t1 >= t0) and np.all(t3 >= t2)):
        raise ValueError("expected window times with T0 <= T1 <= T2 <= T3")
    # T1 == T2 is a held keyframe: s = 0 reproduces it.
    s = np.where(span > 0, np.clip((q - t1) / np.where(span > 0, span, 1.0), 0.0, 1.0), 0.0)
    d0 = _dq_rows(_rows(p[..., 0, :]))
    d1 = _dq_rows(_rows(p[..., 1, :]))
    d2 = _dq_rows(_rows(p[..., 2, :]))
    d3 = _dq_rows(_rows(p[..., 3, :]))
    # Sign choices chained keyframe to keyframe, so neighbouring segments agree.
    d0, _ = _align_to(d1, d0)
    d2, _ = _align_to(d1, d2)
    d3, _ = _align_to(d2, d3)
    chord = d2 - d1
    w0 = t2 - t0
    w3 = t3 - t1
    m1 = np.where(t1 > t0, (d2 - d0) * (span / np.where(w0 > 0, w0, 1.0)), chord)
    m2 = np.where(t3 > t2, (d3 - d1) * (span / np.where(w3 > 0, w3, 1.0)), chord)
    rows = _dq_to_pose_rows(_hermite(d1, d2, m1, m2, s))
    return _finish(rows, batch, s, p[..., 1, :], p[..., 2, :])


def _dq_rate_rows(d: F64, vel: F64) -> F64:
    """Time derivative of dual-quaternion rows for world-frame velocities (6, M).

    ``qr' = 1/2 w qr`` and, from ``qd = 1/2 t qr``, ``qd' = 1/2 (v qr + t qr')``,
    with ``v``, ``w`` and ``t`` as pure quaternions.
    """
    w, x, y, z = d[:4]
    vx, vy, vz, ax, ay, az = vel
    # qr' = 1/2 (0, a) qr
    rw = 0.5 * (-ax * x - ay * y - az * z)
    rx = 0.5 * (ax * w + ay * z - az * y)
    ry = 0.5 * (-ax * z + ay * w + az * x)
    rz = 0.5 * (ax * y - ay * x + az * w)
    # t = 2 qd qr* (vector part), recovered from the unit dual quaternion
    dw, dx, dy, dz = d[4:]
    tx = 2.0 * (-dw * x + dx * w - dy * z + dz * y)
    ty = 2.0 * (-dw * y + dx * z + dy * w - dz * x)
    tz = 2.0 * (-dw * z - dx * y + dy * x + dz * w)
    # qd' = 1/2 ((0, v) qr + (0, t) qr')
    return np.stack(
        [
            rw,
            rx,
            ry,
            rz,
            0.5 * ((-vx * x - vy * y - vz * z) + (-tx * rx - ty * ry - tz * rz)),
            0.5 * ((vx * w + vy * z - vz * y) + (tx * rw + ty * rz - tz * ry)),
            0.5 * ((-vx * z + vy * w + vz * x) + (-tx * rz + ty * rw + tz * rx)),
            0.5 * ((vx * y - vy * x + vz * w) + (tx * ry - ty * rx + tz * rw)),
        ]
    )


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
    """
    pa = _checked(a, "a", (7,))
    pb = _checked(b, "b", (7,))
    if pa.shape != pb.shape:
        pa, pb = np.broadcast_arrays(pa, pb)
    batch = pa.shape[:-1]
    vva = np.broadcast_to(_checked(va, "va", (VELOCITY_SIZE,)), (*batch, VELOCITY_SIZE))
    vvb = np.broadcast_to(_checked(vb, "vb", (VELOCITY_SIZE,)), (*batch, VELOCITY_SIZE))
    span = np.broadcast_to(_checked(dt, "dt", ()), batch).reshape(-1)
    if not np.all(span > 0):
        raise ValueError("expected `dt` to be positive")
    ss = np.broadcast_to(_checked(s, "s", ()), batch).reshape(-1).astype(np.float64)
    d1 = _dq_rows(_rows(pa))
    d2 = _dq_rows(_rows(pb))
    m1 = _dq_rate_rows(d1, _rows(vva)) * span
    d2, sign = _align_to(d1, d2)
    # The derivative of -M is -M': flip it with its motor.
    m2 = _dq_rate_rows(d2 * sign, _rows(vvb)) * (span * sign)
    rows = _dq_to_pose_rows(_hermite(d1, d2, m1, m2, ss))
    return _finish(rows, batch, ss, pa, pb)


def screw_extrapolate(a: ArrayLike, b: ArrayLike, s: ArrayLike, max_s: float = 2.0) -> F64:
    """Continue the screw motion from ``a`` to ``b`` to fraction ``s >= 1``.

    ``s`` is clipped to ``[0, max_s]``: a bounded horizon, so a lost stream
    drifts at most ``max_s - 1`` keyframe intervals past its newest keyframe.
    """
    return dq_slerp(a, b, np.clip(np.asarray(s, dtype=np.float64), 0.0, max_s))
