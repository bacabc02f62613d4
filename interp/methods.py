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

``out=`` (keyword; a writeable C-contiguous float64 array of the result's shape)
receives the result instead of a new array: a caller that interpolates batch
after batch then allocates nothing, whatever the allocator does with large
blocks (glibc maps and unmaps them per call when its dynamic threshold is off).

Every ``sin(x)/sin(y)`` ratio is taken directly (both sines are accurate to an ulp
at any angle) with its limit substituted only at an exactly zero angle, so tiny
rotations are as exact as large ones, without branches.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from posecast.interp.kernels import (
    CHUNK,
    RowKernel,
    dq_slerp_rows,
    hemisphere_sign,
    motor_lerp_rows,
    scratch,
    soa_rows,
)
from posecast.interp.pose import F64, UNIT_TOLERANCE

__all__ = ["dq_slerp", "hemisphere_sign", "motor_lerp", "prepare", "soa"]


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
    a_n, b_n, s_n, batch = _check_args(a, b, s)
    return _validate_rows(_rows(a_n), "a"), _validate_rows(_rows(b_n), "b"), s_n, batch


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


def _check_args(a: ArrayLike, b: ArrayLike, s: ArrayLike) -> tuple[F64, F64, F64, tuple[int, ...]]:
    """``a``, ``b`` as ``(N, 7)``, ``s`` as ``(N,)`` (views where possible), and the
    batch shape, checked.

    Raises the errors :func:`prepare` raises; quaternion norms are checked per
    chunk by :func:`_chunk_rows`.
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
    return a_arr.reshape(-1, 7), b_arr.reshape(-1, 7), s_b.reshape(-1), batch


def _chunk_rows(rows: F64, poses: F64, name: str, n2: F64, t4: F64, off: NDArray[np.bool_]) -> None:
    """Copy ``poses (M, 7)`` into ``rows (7, M)`` and check them; quaternions off
    unit length by more than the tolerance are normalised, each on its own (so a
    pose's result does not depend on the others in its batch or chunk).

    ``n2``, ``t4``, ``off``: scratch rows.
    """
    np.copyto(rows, poses.T)
    if not np.isfinite(rows.sum()) and not np.all(np.isfinite(rows)):
        raise ValueError(f"expected `{name}` to hold finite values")
    q = rows[3:]
    np.multiply(q, q, out=t4)
    np.add.reduce(t4, axis=0, out=n2)
    lo, hi = float(n2.min()), float(n2.max())
    # |q|^2 - 1 ~ 2 (|q| - 1): compare squared norms to twice the tolerance.
    if abs(lo - 1.0) > 2.0 * UNIT_TOLERANCE or abs(hi - 1.0) > 2.0 * UNIT_TOLERANCE:
        if not lo > 1e-24:
            raise ValueError(f"expected `{name}` to hold non-zero quaternions")
        np.greater(np.abs(n2 - 1.0), 2.0 * UNIT_TOLERANCE, out=off)
        np.sqrt(n2, out=n2)
        np.divide(q, n2, out=q, where=off)


def _out_rows(out: F64, a: F64, b: F64, batch: tuple[int, ...]) -> F64 | None:
    """``out`` as ``(N, 7)`` rows to write into, or None when it overlaps ``a`` or ``b``
    (then the result is computed apart and copied)."""
    shape = (*batch, 7)
    if not (
        isinstance(out, np.ndarray)
        and out.dtype == np.float64
        and out.shape == shape
        and out.flags.c_contiguous
        and out.flags.writeable
    ):
        got = f"{out.dtype} {out.shape}" if isinstance(out, np.ndarray) else type(out).__name__
        raise ValueError(
            f"expected `out` to be a writeable C-contiguous float64 array of shape {shape}, "
            f"got {got}"
        )
    if np.may_share_memory(out, a) or np.may_share_memory(out, b):
        return None
    return out.reshape(-1, 7)


def _pair(
    kernel: RowKernel, a: ArrayLike, b: ArrayLike, s: ArrayLike, out: F64 | None = None
) -> F64:
    """Run a row kernel over ``a``, ``b``, ``s`` chunk by chunk into one ``(..., 7)`` result
    (into ``out`` if given).

    Each chunk of poses is copied component-major into this thread's scratch,
    validated there and interpolated straight into the result's rows: besides
    the result, a call allocates nothing that grows with the batch, and with
    ``out`` nothing at all.
    """
    a2, b2, s1, batch = _check_args(a, b, s)
    n = a2.shape[0]
    rows = None if out is None else _out_rows(out, a2, b2, batch)
    res = np.empty((n, 7)) if rows is None else rows
    unit_s = n > 0 and float(np.min(s1)) >= 0.0 and float(np.max(s1)) <= 1.0
    for i in range(0, n, CHUNK):
        j = min(n, i + CHUNK)
        work = scratch(j - i)
        A, B = work[0][0:7], work[0][7:14]
        # Rows 14.. of the scratch are the kernel's; borrow two before it runs.
        scratch_rows = (work[0][14], work[0][15:19], work[1][0])
        _chunk_rows(A, a2[i:j], "a", *scratch_rows)
        _chunk_rows(B, b2[i:j], "b", *scratch_rows)
        kernel(A, B, s1[i:j], res[i:j].T, work, unit_s)
    if out is None:
        return res.reshape((*batch, 7))
    if rows is None:  # out overlaps the input: written only now
        np.copyto(out, res.reshape(out.shape))
    return out


def soa(a: ArrayLike, b: ArrayLike, s: ArrayLike, *, out: F64 | None = None) -> F64:
    """Position LERP + shortest-path quaternion SLERP.

    With ``q1`` in ``q0``'s hemisphere and the angle ``w`` between them taken from
    the half chords ``|q1 - q0| = 2 sin(w/2)`` and ``|q1 + q0| = 2 cos(w/2)``
    (accurate near 0, unlike ``acos(q0.q1)``; ``sin w = |d| |m| / 2`` without
    trig)::

        t = t0 + s (t1 - t0)
        q = [sin((1-s) w) q0 + sin(s w) q1] / sin w,   sin((1-s) w) = sin w cos sw - cos w sin sw

    with the limits ``1 - s`` and ``s`` of the two weights at ``w = 0``.
    """
    return _pair(soa_rows, a, b, s, out)


def dq_slerp(a: ArrayLike, b: ArrayLike, s: ArrayLike, *, out: F64 | None = None) -> F64:
    """Dual-quaternion ScLERP: constant-speed screw motion from ``a`` to ``b``.

    With the relative motion ``q_d = q0* q1 = (cos phi, sin phi u)`` and
    ``t_d = R0^T (t1 - t0)``, the screw at fraction s rotates by ``2 s phi``
    about ``u`` and advances ``s (t_d.u) u`` along it, while the perpendicular
    part ``t_perp`` moves on the circle about the screw axis:
    ``sin(s phi)/sin(phi) Rot(u, -(1-s) phi) t_perp``. In full::

        k = sin(s phi) / sin(phi),  kr = sin((1-s) phi) / sin(phi),  kc = k cos((1-s) phi)
        t_rel = kc t_d + (s - kc) (t_d.u) u - k kr (v x t_d),   v = sin(phi) u
        t = t0 + R0 t_rel,   q = q0 (cos(s phi), k v)
    """
    return _pair(dq_slerp_rows, a, b, s, out)


def motor_lerp(a: ArrayLike, b: ArrayLike, s: ArrayLike, *, out: F64 | None = None) -> F64:
    """Motor LERP: blend ``(1-s) M0 + s M1`` and divide by its Study number.

    In (t, q) form, with ``c = q0 q1*`` (``c_w = q0.q1 >= 0`` after alignment),
    the normalised blend has rotation ``nlerp(q0, q1, s)`` and translation

        [(1-s)^2 t0 + s^2 t1 + s(1-s) (c_w (t0 + t1) + (t0 - t1) x c_v)]
        / [(1-s)^2 + s^2 + 2 s (1-s) c_w]

    The Study number's dual part only changes the scalar part of ``2 qd qr*``,
    which this form never computes, so the result is the properly normalised
    motor's pose (dividing by ``sqrt(S)`` alone would leave a non-rigid motor).
    """
    return _pair(motor_lerp_rows, a, b, s, out)
