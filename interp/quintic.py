"""A C2 quintic on motors over a wide window of keyframes: ``motor-quintic``.

Catmull-Rom (``motor-cubic``) estimates the velocity at a keyframe from its two
neighbours (a parabola through three keyframes) and ignores the acceleration.
``motor-quintic`` estimates both from the **quartic through five keyframes**
``k-2 .. k+2`` around each keyframe ``k`` (non-uniform times: the derivatives at
``t_k`` of the Lagrange polynomial), then joins the bracket ``[lo, hi]`` with
the quintic Hermite curve that matches position, velocity and acceleration at
both ends. The window is six keyframes, two either side of the bracket
(``lookbehind = lookahead = 2``): one interval of playout delay more than
``motor-cubic``.

Everything happens on the motors (unit dual quaternions; a motor is one under
a fixed linear map): the curve is a fixed linear combination of the window's
motors, with weights that depend on the times only, followed by Study-number
normalisation (as ``motor-lerp`` and ``motor-cubic``). A linear combination of
motors commutes with multiplying all of them by a fixed motor on either side,
and so does the normalisation, so the curve commutes with a change of world
frame *and* of body frame: position and rotation stay one rigid motion. Signs
are chained keyframe to keyframe outwards from ``lo``, so neighbouring windows
agree and the curve is blind to each keyframe's quaternion sign.

Properties:

- It passes through the keyframes (``s = 0`` and ``1`` return ``lo`` and ``hi``
  bit for bit).
- With complete windows, the stencil at keyframe ``k`` is the same for the two
  segments meeting there, so the motor curve, hence the pose, is C2 (position,
  velocity and acceleration continuous) across keyframes.
- Motor curves that are polynomials of degree <= 4 in time (e.g. any translation
  along a quartic path at a fixed orientation) are reproduced exactly.
- Missing neighbours (``interp.registry``'s rule: a neighbour repeating its
  inward neighbour's time) drop out of the stencil: at a track end the velocity
  and acceleration come from the lower-degree polynomial through the keyframes
  that exist; with only the bracket it is a linear motor blend (motor-LERP).

Why not a polynomial in the Lie algebra (logs of relative motors)? That is also
bi-invariant, but needs a log per keyframe and an exp per query, several times
the cost, for keyframes that are well under a half turn apart, where the
normalised linear blend and the screw agree closely (motor-LERP equals ScLERP
at s = 1/2). And a local least-squares fit would not pass through the
keyframes, which are exact samples of the true motion.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from interp.cubic import _align_to, _checked, _dq_rows, _dq_to_pose_rows, _finish
from interp.methods import _rows
from interp.pose import F64

__all__ = ["QUINTIC_LOOKAHEAD", "QUINTIC_LOOKBEHIND", "motor_quintic", "motor_window_spline"]

QUINTIC_LOOKBEHIND = 2
QUINTIC_LOOKAHEAD = 2


def _stencil_weights(
    x: list[F64], ok: list[F64], i: int, nodes: range
) -> tuple[dict[int, F64], dict[int, F64]]:
    """First and second derivative weights at node ``i`` of the polynomial through ``nodes``.

    ``x`` are node times (``(M,)`` each, in units of the bracket span), ``ok``
    1.0 where a node is available. Unavailable nodes get weight 0 and drop out
    of the polynomial. Returns ``{j: L_j'(x_i)}`` and ``{j: L_j''(x_i)}``,
    including ``j = i`` (minus the sum of the others: constants have no
    derivative).
    """
    others = [j for j in nodes if j != i]
    here = ok[i] > 0
    avail = {j: (ok[j] > 0) & here for j in others}
    u = {j: np.where(avail[j], x[j] - x[i], 1.0) for j in others}
    inv = {j: np.where(avail[j], -1.0 / u[j], 0.0) for j in others}  # 1/(x_i - x_j)
    d1: dict[int, F64] = {}
    d2: dict[int, F64] = {}
    for j in others:
        # L_j'(x_i) = prod_{m != i, j} (x_i - x_m) / (x_j - x_m) / (x_j - x_i)
        w = 1.0 / u[j]
        acc = np.zeros_like(w)
        for m in others:
            if m == j:
                continue
            both = avail[m] & avail[j]
            w = w * np.where(both, -u[m] / np.where(both, u[j] - u[m], 1.0), 1.0)
            acc = acc + inv[m]
        w = np.where(avail[j], w, 0.0)
        d1[j] = w
        # L_j''(x_i) = 2 L_j'(x_i) * sum_{m != i, j} 1 / (x_i - x_m)
        d2[j] = 2.0 * w * acc
    d1[i] = -sum(d1.values(), np.zeros_like(x[i]))
    d2[i] = -sum(d2.values(), np.zeros_like(x[i]))
    return d1, d2


def _quintic_basis(s: F64) -> tuple[F64, F64, F64, F64, F64, F64]:
    """Quintic Hermite basis: p0, v0, a0, a1, v1, p1 (unit interval)."""
    s2 = s * s
    s3 = s2 * s
    s4 = s3 * s
    s5 = s4 * s
    h_p1 = 10.0 * s3 - 15.0 * s4 + 6.0 * s5
    h_p0 = 1.0 - h_p1
    h_v0 = s - 6.0 * s3 + 8.0 * s4 - 3.0 * s5
    h_v1 = -4.0 * s3 + 7.0 * s4 - 3.0 * s5
    h_a0 = 0.5 * (s2 - 3.0 * s3 + 3.0 * s4 - s5)
    h_a1 = 0.5 * (s3 - 2.0 * s4 + s5)
    return h_p0, h_v0, h_a0, h_a1, h_v1, h_p1


def motor_window_spline(
    keys: ArrayLike, times: ArrayLike, t: ArrayLike, lookbehind: int, lookahead: int
) -> F64:
    """The C2 motor quintic over a window of ``lookbehind + 2 + lookahead`` keyframes.

    The velocity and acceleration at each bracket keyframe ``k`` come from the
    polynomial through keyframes ``k - lookbehind .. k + lookahead`` (so both
    segments meeting at ``k`` use the same ones). ``keys (..., K, 7)``,
    ``times (..., K)`` non-decreasing (window layout and missing neighbours as
    in :mod:`interp.registry`), ``t`` broadcastable to the batch shape.
    """
    if lookbehind < 0 or lookahead < 0:
        raise ValueError("expected lookbehind, lookahead >= 0")
    lo, hi = lookbehind, lookbehind + 1
    k = lookbehind + 2 + lookahead
    p = _checked(keys, "keys", (k, 7))
    tt = _checked(times, "times", (k,))
    batch = p.shape[:-2]
    if tt.shape[:-1] != batch:
        try:
            tt = np.broadcast_to(tt, (*batch, k))
        except ValueError:
            raise ValueError(
                f"expected `times` of shape {(*batch, k)} to match `keys`, got {tt.shape}"
            ) from None
    tq = _checked(t, "t", ())
    try:
        q = np.broadcast_to(tq, batch).reshape(-1).astype(np.float64)
    except ValueError:
        raise ValueError(f"expected `t` broadcastable to {batch}") from None
    T = _rows(tt)
    if k > 1 and not np.all(T[1:] >= T[:-1]):
        raise ValueError("expected non-decreasing window `times`")
    span = T[hi] - T[lo]
    held = span <= 0
    h = np.where(held, 1.0, span)
    s = np.where(held, 0.0, np.clip((q - T[lo]) / h, 0.0, 1.0))
    # Available nodes: the bracket, and neighbours outwards until the first repeat.
    ok: list[F64] = [np.ones_like(span)] * k
    ok[hi] = (~held).astype(np.float64)
    for j in range(lo - 1, -1, -1):
        ok[j] = ok[j + 1] * (T[j] < T[j + 1])
    for j in range(hi + 1, k):
        ok[j] = ok[j - 1] * (T[j] > T[j - 1])
    x = [(T[j] - T[lo]) / h for j in range(k)]
    v_lo, a_lo = _stencil_weights(x, ok, lo, range(lo - lookbehind, lo + lookahead + 1))
    v_hi, a_hi = _stencil_weights(x, ok, hi, range(hi - lookbehind, hi + lookahead + 1))
    b_p0, b_v0, b_a0, b_a1, b_v1, b_p1 = _quintic_basis(s)
    # Motor of each keyframe, signs chained outwards from lo.
    d: list[F64] = [_dq_rows(_rows(p[..., j, :])) for j in range(k)]
    for j in range(lo + 1, k):
        d[j], _ = _align_to(d[j - 1], d[j])
    for j in range(lo - 1, -1, -1):
        d[j], _ = _align_to(d[j + 1], d[j])
    blend = np.zeros_like(d[lo])
    for j in range(k):
        c = (
            b_v0 * v_lo.get(j, 0.0)
            + b_v1 * v_hi.get(j, 0.0)
            + b_a0 * a_lo.get(j, 0.0)
            + b_a1 * a_hi.get(j, 0.0)
        )
        if j == lo:
            c = c + b_p0
        elif j == hi:
            c = c + b_p1
        blend += c * d[j]
    rows = _dq_to_pose_rows(blend)
    return _finish(rows, batch, s, p[..., lo, :], p[..., hi, :])


def motor_quintic(keys: ArrayLike, times: ArrayLike, t: ArrayLike) -> F64:
    """C2 quintic on motors through a window of 6 keyframes (2 each side), at times ``t``."""
    return motor_window_spline(keys, times, t, QUINTIC_LOOKBEHIND, QUINTIC_LOOKAHEAD)
