"""Pose representations and the quaternion algebra under them.

A pose is 7 numbers ``[px, py, pz, qw, qx, qy, qz]`` (metres, unit quaternion,
w first); arrays of poses have shape ``(..., 7)``. This module owns input
validation, conversions between poses and (t, q), unit dual quaternions, 3D PGA
motors and 4x4 matrices, and the quaternion product, conjugate and rotation of
vectors. Everything is vectorised over leading axes and computed in float64.

Dual quaternions are 8 numbers ``[rw, rx, ry, rz, dw, dx, dy, dz]`` for
``qr + eps qd`` with ``qd = 1/2 t qr``.

Motors use the paper's convention and coefficient order
``(1, e01, e02, e03, e12, e13, e23, e0123)`` with translator
``T = 1 - 1/2 e0 (t1 e1 + t2 e2 + t3 e3)``, rotor ``R = w - x e23 + y e13 - z e12``
and ``M = T R``. Under ``i = -e23, j = e13, k = -e12, eps = e0123`` a motor is the
dual quaternion ``qr - eps (1/2 t qr)``: a fixed linear map of the 8 coefficients.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "F64",
    "UNIT_TOLERANCE",
    "as_pose",
    "as_quat",
    "dq_to_pose",
    "matrix_to_pose",
    "motor_to_pose",
    "pose_from_tq",
    "pose_to_dq",
    "pose_to_matrix",
    "pose_to_motor",
    "pose_to_tq",
    "quat_conj",
    "quat_mul",
    "quat_rotate",
]

F64 = NDArray[np.float64]

#: Quaternions further than this from unit norm are renormalised on input.
UNIT_TOLERANCE = 1e-6


def _check_last_axis(x: NDArray[np.float64], n: int, name: str) -> None:
    if x.ndim == 0 or x.shape[-1] != n:
        raise ValueError(f"expected `{name}` to have shape (..., {n}), got {x.shape}")


def _as_float_array(x: ArrayLike, name: str) -> F64:
    try:
        arr = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"expected `{name}` to be a float array: {exc}") from None
    return arr


def _unit_norm_sq(q: F64, name: str) -> tuple[F64, bool]:
    """Squared norms of quaternions ``q``; also whether any is off unit length."""
    n2: F64 = np.einsum("...i,...i->...", q, q)
    if not np.all(n2 > 1e-24):
        raise ValueError(f"expected `{name}` to hold non-zero quaternions")
    # |q|^2 - 1 ~ 2 (|q| - 1): compare squared norms to twice the tolerance.
    return n2, bool(np.any(np.abs(n2 - 1.0) > 2.0 * UNIT_TOLERANCE))


def _normalise_quats(q: F64, name: str) -> F64:
    """Return ``q`` with unit rows; reject zero norms; copy only when needed."""
    n2, off = _unit_norm_sq(q, name)
    if off:
        q = q / np.sqrt(n2)[..., None]
    return q


def as_pose(x: ArrayLike, name: str = "pose") -> F64:
    """Validate ``x`` as poses ``(..., 7)``: finite, non-zero quaternions.

    Quaternions off unit length by more than :data:`UNIT_TOLERANCE` are
    normalised (the input is not modified).
    """
    arr = _as_float_array(x, name)
    _check_last_axis(arr, 7, name)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"expected `{name}` to hold finite values")
    n2, off = _unit_norm_sq(arr[..., 3:], name)
    if off:
        arr = arr.copy()
        arr[..., 3:] /= np.sqrt(n2)[..., None]
    return arr


def as_quat(x: ArrayLike, name: str = "q") -> F64:
    """Validate ``x`` as quaternions ``(..., 4)`` (w first), normalising if needed."""
    arr = _as_float_array(x, name)
    _check_last_axis(arr, 4, name)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"expected `{name}` to hold finite values")
    return _normalise_quats(arr, name)


def quat_mul(p: ArrayLike, q: ArrayLike) -> F64:
    """Hamilton product ``p q`` of quaternions ``(..., 4)``, w first."""
    p = np.asarray(p, dtype=np.float64)
    q = np.asarray(q, dtype=np.float64)
    pw, px, py, pz = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    qw, qx, qy, qz = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def quat_conj(q: ArrayLike) -> F64:
    """Conjugate (the inverse of a unit quaternion)."""
    out = np.array(q, dtype=np.float64, copy=True)
    out[..., 1:] *= -1.0
    return out


def quat_rotate(q: ArrayLike, v: ArrayLike) -> F64:
    """Rotate vectors ``v (..., 3)`` by unit quaternions ``q (..., 4)``."""
    q = np.asarray(q, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    w = q[..., :1]
    u = q[..., 1:]
    # v' = v + 2 w (u x v) + 2 u x (u x v): two cross products, no matrix.
    uv = np.cross(u, v)
    return v + 2.0 * (w * uv + np.cross(u, uv))


def pose_to_tq(pose: ArrayLike) -> tuple[F64, F64]:
    """Split poses into translations ``(..., 3)`` and unit quaternions ``(..., 4)``."""
    p = as_pose(pose)
    return p[..., :3], p[..., 3:]


def pose_from_tq(t: ArrayLike, q: ArrayLike) -> F64:
    """Join translations ``(..., 3)`` and quaternions ``(..., 4)`` into poses."""
    t_arr = _as_float_array(t, "t")
    _check_last_axis(t_arr, 3, "t")
    q_arr = as_quat(q)
    try:
        batch = np.broadcast_shapes(t_arr.shape[:-1], q_arr.shape[:-1])
    except ValueError:
        raise ValueError(
            f"expected `t` (..., 3) and `q` (..., 4) with matching leading shapes, "
            f"got {t_arr.shape} and {q_arr.shape}"
        ) from None
    return np.concatenate(
        [np.broadcast_to(t_arr, (*batch, 3)), np.broadcast_to(q_arr, (*batch, 4))], axis=-1
    )


def pose_to_dq(pose: ArrayLike) -> F64:
    """Unit dual quaternions ``(..., 8)``: ``qr`` then ``qd = 1/2 t qr``."""
    t, q = pose_to_tq(pose)
    tq = np.concatenate([np.zeros_like(t[..., :1]), t], axis=-1)
    return np.concatenate([q, 0.5 * quat_mul(tq, q)], axis=-1)


def dq_to_pose(dq: ArrayLike) -> F64:
    """Poses from dual quaternions ``(..., 8)``, normalising them first.

    Normalisation divides by the dual number ``|qr| + eps (qr.qd)/|qr|``; the
    translation ``2 qd qr*`` only needs the real part, because the dual part of
    the norm changes the scalar part alone.
    """
    d = _as_float_array(dq, "dq")
    _check_last_axis(d, 8, "dq")
    if not np.all(np.isfinite(d)):
        raise ValueError("expected `dq` to hold finite values")
    qr, qd = d[..., :4], d[..., 4:]
    n2 = np.einsum("...i,...i->...", qr, qr)
    if not np.all(n2 > 1e-24):
        raise ValueError("expected `dq` to have a non-zero real part")
    t = 2.0 * quat_mul(qd, quat_conj(qr))[..., 1:] / n2[..., None]
    return np.concatenate([t, qr / np.sqrt(n2)[..., None]], axis=-1)


def pose_to_motor(pose: ArrayLike) -> F64:
    """3D PGA motors ``(..., 8)`` in the order (1, e01, e02, e03, e12, e13, e23, e0123)."""
    dq = pose_to_dq(pose)
    rw, rx, ry, rz = dq[..., 0], dq[..., 1], dq[..., 2], dq[..., 3]
    # The paper's translator carries -t, so the motor's dual part is -qd.
    dw, dx, dy, dz = -dq[..., 4], -dq[..., 5], -dq[..., 6], -dq[..., 7]
    return np.stack([rw, dx, dy, dz, -rz, ry, -rx, dw], axis=-1)


def motor_to_pose(motor: ArrayLike) -> F64:
    """Poses from motors ``(..., 8)`` (normalised by their Study number first)."""
    m = _as_float_array(motor, "motor")
    _check_last_axis(m, 8, "motor")
    dq = np.stack(
        [
            m[..., 0],
            -m[..., 6],
            m[..., 5],
            -m[..., 4],
            -m[..., 7],
            -m[..., 1],
            -m[..., 2],
            -m[..., 3],
        ],
        axis=-1,
    )
    return dq_to_pose(dq)


def pose_to_matrix(pose: ArrayLike) -> F64:
    """Homogeneous 4x4 matrices ``(..., 4, 4)``."""
    t, q = pose_to_tq(pose)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    m = np.zeros((*q.shape[:-1], 4, 4))
    m[..., 0, 0] = 1 - 2 * (y * y + z * z)
    m[..., 0, 1] = 2 * (x * y - w * z)
    m[..., 0, 2] = 2 * (x * z + w * y)
    m[..., 1, 0] = 2 * (x * y + w * z)
    m[..., 1, 1] = 1 - 2 * (x * x + z * z)
    m[..., 1, 2] = 2 * (y * z - w * x)
    m[..., 2, 0] = 2 * (x * z - w * y)
    m[..., 2, 1] = 2 * (y * z + w * x)
    m[..., 2, 2] = 1 - 2 * (x * x + y * y)
    m[..., :3, 3] = t
    m[..., 3, 3] = 1.0
    return m


def matrix_to_pose(matrix: ArrayLike) -> F64:
    """Poses from homogeneous matrices ``(..., 4, 4)`` with a rotation block.

    Uses the numerically robust branch choice (largest of w, x, y, z first), and
    returns the quaternion with w >= 0.
    """
    m = _as_float_array(matrix, "matrix")
    if m.ndim < 2 or m.shape[-2:] != (4, 4):
        raise ValueError(f"expected `matrix` to have shape (..., 4, 4), got {m.shape}")
    if not np.all(np.isfinite(m)):
        raise ValueError("expected `matrix` to hold finite values")
    r = m[..., :3, :3]
    tr = r[..., 0, 0] + r[..., 1, 1] + r[..., 2, 2]
    # 4 candidate quaternions scaled by 4*component; pick the best-conditioned one.
    cands = np.stack(
        [
            np.stack(
                [
                    1 + tr,
                    r[..., 2, 1] - r[..., 1, 2],
                    r[..., 0, 2] - r[..., 2, 0],
                    r[..., 1, 0] - r[..., 0, 1],
                ],
                axis=-1,
            ),
            np.stack(
                [
                    r[..., 2, 1] - r[..., 1, 2],
                    1 + r[..., 0, 0] - r[..., 1, 1] - r[..., 2, 2],
                    r[..., 0, 1] + r[..., 1, 0],
                    r[..., 0, 2] + r[..., 2, 0],
                ],
                axis=-1,
            ),
            np.stack(
                [
                    r[..., 0, 2] - r[..., 2, 0],
                    r[..., 0, 1] + r[..., 1, 0],
                    1 - r[..., 0, 0] + r[..., 1, 1] - r[..., 2, 2],
                    r[..., 1, 2] + r[..., 2, 1],
                ],
                axis=-1,
            ),
            np.stack(
                [
                    r[..., 1, 0] - r[..., 0, 1],
                    r[..., 0, 2] + r[..., 2, 0],
                    r[..., 1, 2] + r[..., 2, 1],
                    1 - r[..., 0, 0] - r[..., 1, 1] + r[..., 2, 2],
                ],
                axis=-1,
            ),
        ],
        axis=-2,
    )
    diag = np.stack([1 + tr, cands[..., 1, 1], cands[..., 2, 2], cands[..., 3, 3]], axis=-1)
    best = np.argmax(diag, axis=-1)
    q = np.take_along_axis(cands, best[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    q = np.where(q[..., :1] < 0, -q, q)
    return np.concatenate([m[..., :3, 3], q], axis=-1)
