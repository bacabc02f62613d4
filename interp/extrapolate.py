"""Dead reckoning from one keyframe and its velocity (constant-twist motion).

:func:`twist_extrapolate` continues a pose with the velocity the tracker
reported with it, assuming the **spatial twist** stays constant: the rigid
motion keeps turning about the same screw axis at the same rates. With world
frame velocities ``v`` (of the device origin, m/s) and ``w`` (rad/s) and the
rotation vector ``phi = w dt``:

    q(dt) = exp(phi / 2) q
    p(dt) = p + dt J(phi) v,   J = a I + b [phi]x + c phi phi^T

with ``a = sin(t)/t``, ``b = (1 - cos t)/t^2``, ``c = (t - sin t)/t^3`` and
``t = |phi|`` (the left Jacobian of SO(3); series near ``t = 0``). This is the
motion a constant screw makes, so it agrees with ScLERP continued past ``s = 1``
along a constant screw, and with ``motor-hermite`` fed that screw's velocities.
It commutes with a change of world frame (the velocities transform with it) and
with a change of body frame (the origin velocity of the new body point is what
the twist gives it).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from posecast.interp.pose import F64, as_pose

__all__ = ["twist_extrapolate"]

#: Below this rotation angle (rad) the Jacobian coefficients use their series.
_SMALL_ANGLE = 1e-3


def _cross(u: F64, v: F64) -> F64:
    """``u x v`` over the last axis (np.cross costs more than the arithmetic here)."""
    out = np.empty(np.broadcast_shapes(u.shape, v.shape))
    out[..., 0] = u[..., 1] * v[..., 2] - u[..., 2] * v[..., 1]
    out[..., 1] = u[..., 2] * v[..., 0] - u[..., 0] * v[..., 2]
    out[..., 2] = u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]
    return out


def twist_extrapolate(pose: ArrayLike, velocity: ArrayLike, dt: ArrayLike) -> F64:
    """``pose (..., 7)`` moved for ``dt`` seconds at constant twist ``velocity (..., 6)``.

    ``velocity`` is linear (m/s) then angular (rad/s), both in the world frame;
    ``dt`` broadcasts to the batch and may be negative (dead reckoning backwards).
    """
    p = as_pose(pose, "pose")
    vel = np.asarray(velocity, dtype=np.float64)
    if vel.ndim == 0 or vel.shape[-1] != 6:
        raise ValueError(f"expected `velocity` to have shape (..., 6), got {vel.shape}")
    batch = np.broadcast_shapes(p.shape[:-1], vel.shape[:-1], np.shape(dt))
    p = np.broadcast_to(p, (*batch, 7))
    v = np.broadcast_to(vel[..., :3], (*batch, 3))
    tau = np.broadcast_to(np.asarray(dt, dtype=np.float64), batch)[..., None]
    if not (np.all(np.isfinite(vel)) and np.all(np.isfinite(tau))):
        raise ValueError("expected finite `velocity` and `dt`")
    phi = np.broadcast_to(vel[..., 3:], (*batch, 3)) * tau
    th2 = np.einsum("...i,...i->...", phi, phi)[..., None]
    th = np.sqrt(th2)
    small = th < _SMALL_ANGLE
    safe = np.where(small, 1.0, th)
    sin_t, cos_t = np.sin(th), np.cos(th)
    a = np.where(small, 1.0 - th2 / 6.0, sin_t / safe)
    b = np.where(small, 0.5 - th2 / 24.0, (1.0 - cos_t) / (safe * safe))
    c = np.where(small, 1.0 / 6.0 - th2 / 120.0, (th - sin_t) / (safe * safe * safe))
    phi_dot_v = np.einsum("...i,...i->...", phi, v)[..., None]
    step = a * v + b * _cross(phi, v) + c * phi * phi_dot_v
    out = np.empty((*batch, 7))
    out[..., :3] = p[..., :3] + tau * step
    # exp(phi / 2) q, with cos/sin of the half angle (sinc series near 0).
    half = 0.5 * th
    k = np.where(small, 0.5 - th2 / 48.0, np.sin(half) / safe)
    ew = np.cos(half)[..., 0]
    ev = k * phi
    qw, qv = p[..., 3], p[..., 4:]
    out[..., 3] = ew * qw - np.einsum("...i,...i->...", ev, qv)
    out[..., 4:] = ew[..., None] * qv + qw[..., None] * ev + _cross(ev, qv)
    out[..., 3:] /= np.linalg.norm(out[..., 3:], axis=-1, keepdims=True)
    return out
