"""``soa-hermite``: the SoA split (position and rotation apart) with Hermite curves.

The baseline for ``motor-hermite``: the same inputs (keyframe poses, the
tracker's world-frame linear and angular velocities, the interval), but no
dual quaternions or motors. Position and rotation are interpolated separately,
as engines do with LERP + SLERP, each by a cubic Hermite curve matching the
reported velocities, so the comparison isolates what the rigid-motion algebra
adds over the velocities alone.

Position: the cubic Hermite curve

    p(s) = h00 p_a + h10 dt v_a + h01 p_b + h11 dt v_b

with ``h00 = 1 - 3s^2 + 2s^3``, ``h10 = s - 2s^2 + s^3``, ``h01 = 3s^2 - 2s^3``,
``h11 = s^3 - s^2``.

Rotation: a cubic Hermite curve on the rotation vector in the body frame of
``q_a`` (the tangent space of SO(3) at the first keyframe):

    q(s) = q_a exp(r(s) / 2),
    r(s) = h10 dt w_a + h01 r_1 + h11 dt J_r^-1(r_1) w_b,

with ``r_1 = log(q_a* q_b)`` (``q_b`` in ``q_a``'s hemisphere, so
``|r_1| <= pi``), ``w_a = R_a^T omega_a`` and ``w_b = R_b^T omega_b`` the
angular velocities in body coordinates, and ``J_r^-1`` the inverse right
Jacobian of SO(3),

    J_r^-1(r) w = w + 1/2 r x w + (1 - (th/2) cot(th/2)) / th^2  r x (r x w),

``th = |r|`` (Sola, Deray and Atchuthan, "A micro Lie theory for state
estimation in robotics", arXiv:1812.01537, 2018, eqs. 143-145; Kim, Kim and
Shin, "A general construction scheme for unit quaternion curves with simple
high order derivatives", SIGGRAPH 1995, for quaternion Hermite curves through
the exponential map). A curve ``q_a exp(r(t)/2)`` has body angular velocity
``J_r(r) dr/dt``, so at ``s = 0`` (``r = 0``, ``J_r = I``) the curve turns at
``omega_a`` and at ``s = 1`` at ``omega_b``: both end velocities are matched.
A constant angular velocity about a fixed axis makes ``r`` linear in time with
``J_r^-1(r_1) w_b = w_b = w_a``, which the cubic reproduces exactly.

Properties: ``s = 0`` and ``s = 1`` return the keyframes bit for bit; ``q`` and
``-q`` of either keyframe give the same rotation (at an exact half turn the tie
is broken by :func:`interp.methods.hemisphere_sign`'s rule about rotations);
every step is stable at zero relative rotation (``th/2 = atan2(n, w)``,
``cot(th/2) = w / n`` with their limits) and at a half turn (``(1 -
(th/2) cot(th/2)) / th^2 -> 1/pi^2``). It commutes with a change of world frame
(body-frame rotation vectors do not see it) but, like SoA, not with a change of
body frame: the tracked point's path depends on which point it is.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from posecast.interp.cubic import _exact_ends, _hermite_basis, _hermite_inputs
from posecast.interp.methods import _cross, _qmul, _rotate, hemisphere_sign
from posecast.interp.pose import F64

__all__ = ["soa_hermite"]

#: Below this angle (rad) the Jacobian coefficient uses its Taylor series.
_SERIES_ANGLE = 1e-2


def _log_rows(rel: F64) -> F64:
    """Rotation vectors ``(3, M)`` of unit quaternion rows ``rel (4, M)`` with ``w >= 0``.

    ``r = 2 atan2(n, w) v / n`` (``n = |v|``), with the limit ``2 v / w`` at ``n = 0``.
    """
    w, v = rel[0], rel[1:]
    n = np.sqrt(np.einsum("cm,cm->m", v, v))
    scale = np.full_like(n, 2.0)
    np.divide(2.0 * np.arctan2(n, w), n, out=scale, where=n > 0.0)
    out: F64 = v * scale
    return out


def _exp_rows(r: F64) -> F64:
    """Unit quaternion rows ``exp(r / 2)`` of rotation vectors ``r (3, M)``."""
    th = np.sqrt(np.einsum("cm,cm->m", r, r))
    out = np.empty((4, r.shape[1]))
    out[0] = np.cos(0.5 * th)
    # sin(th/2) / th = sinc(th / (2 pi)) / 2, finite at th = 0.
    out[1:] = r * (0.5 * np.sinc(th / (2.0 * np.pi)))
    return out


def _dexp_inv(r: F64, rel: F64, w: F64) -> F64:
    """``J_r^-1(r) w`` for rotation vectors ``r (3, M)`` of quaternions ``rel`` (``w >= 0``).

    The coefficient ``(1 - x cot x) / th^2`` with ``x = th/2 = atan2(n, rel_w)``
    uses ``cot x = rel_w / n`` (no trigonometry), and its series ``1/12 +
    th^2/720 + th^4/30240`` for small angles; at a half turn ``rel_w = 0`` gives
    ``1 / pi^2``.
    """
    n = np.sqrt(np.einsum("cm,cm->m", rel[1:], rel[1:]))
    half = np.arctan2(n, rel[0])
    th2 = 4.0 * half * half
    big = 2.0 * half >= _SERIES_ANGLE
    coef = 1.0 / 12.0 + th2 * (1.0 / 720.0 + th2 / 30240.0)
    if big.any():
        hb, nb = half[big], n[big]
        coef[big] = (1.0 - hb * rel[0, big] / nb) / th2[big]
    rw = _cross(r, w)
    out: F64 = w + 0.5 * rw + coef * _cross(r, rw)
    return out


def soa_hermite(
    a: ArrayLike,
    b: ArrayLike,
    va: ArrayLike,
    vb: ArrayLike,
    dt: ArrayLike,
    s: ArrayLike,
) -> F64:
    """Cubic Hermite position and quaternion Hermite rotation between ``a`` and ``b``.

    The signature of :func:`interp.cubic.motor_hermite`: ``va``, ``vb`` are
    ``(..., 6)`` world-frame velocities (linear m/s, then angular rad/s) at the
    keyframes, ``dt`` the time between them (s) and ``s`` the fraction in
    ``[0, 1]``. See the module docstring for the curve and its properties.
    """
    batch, span, ss, rows_a, rows_b, A, B, vel_a, vel_b = _hermite_inputs(a, b, va, vb, dt, s)
    qa, qb = A[3:], B[3:]
    dot = np.einsum("cm,cm->m", qa, qb)
    rel = _qmul(qa * np.array([[1.0], [-1.0], [-1.0], [-1.0]]), qb * hemisphere_sign(qa, qb, dot))
    r1 = _log_rows(rel)
    # Body-frame angular velocities (R^T omega; the same for q and -q).
    wa = _rotate(qa, vel_a[3:], inverse=True)
    wb = _dexp_inv(r1, rel, _rotate(qb, vel_b[3:], inverse=True))
    h00, h10, h01, h11 = _hermite_basis(ss)
    c10, c11 = h10 * span, h11 * span
    out = np.empty((7, ss.shape[0]))
    out[:3] = h00 * A[:3] + c10 * vel_a[:3] + h01 * B[:3] + c11 * vel_b[:3]
    q = _qmul(qa, _exp_rows(c10 * wa + h01 * r1 + c11 * wb))
    out[3:] = q / np.sqrt(np.einsum("cm,cm->m", q, q))
    return _exact_ends(out, ss, rows_a, rows_b, batch)
