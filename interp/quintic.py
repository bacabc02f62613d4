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
from numpy.typing import ArrayLike, NDArray

from posecast.interp.cubic import _checked, _float_array, _window_curve
from posecast.interp.methods import _rows
from posecast.interp.pose import F64

__all__ = ["QUINTIC_LOOKAHEAD", "QUINTIC_LOOKBEHIND", "motor_quintic", "motor_window_spline"]

QUINTIC_LOOKBEHIND = 2
QUINTIC_LOOKAHEAD = 2


#: Stand-in offset (in bracket spans) of a missing neighbour: a node this far away
#: drops out of the polynomial (its factors ``u_m / (u_m - u_j)`` round to 1 and
#: its ``1 / u_m`` to nothing against the others) without any branch.
_FAR = 1e30


def _add_derivatives(
    coef: F64, x: list[F64 | float], i: int, nodes: range, bv: F64, ba2: F64
) -> None:
    """``coef[j] += bv L_j'(x_i) + ba2 L_j''(x_i) / 2`` for the polynomial through ``nodes``.

    ``L_j`` are the Lagrange basis polynomials of the node times ``x`` (``(M,)``
    each, in bracket spans; missing nodes at ``+-_FAR``; the bracket's own nodes
    are the plain numbers 0 and 1, which saves whole-array operations), so this
    adds ``bv`` times the velocity and ``ba2 / 2`` times the acceleration at
    node ``i`` as weights of the keyframes. With ``u_m = x_m - x_i``: ``L_j' =
    prod_{m != i} u_m / (u_j^2 prod_{m != i, j} (u_m - u_j))`` and ``L_j'' = 2
    L_j' sum_{m != i, j} (-1 / u_m)`` for ``j != i``; ``L_i^(n) = -sum_{j != i}
    L_j^(n)`` (constants have no derivative). Temporaries are updated in place.
    """
    others = [j for j in nodes if j != i]
    xi = x[i]
    u = {j: (x[j] - xi if isinstance(xi, np.ndarray) or xi != 0.0 else x[j]) for j in others}
    inv = {j: 1.0 / u[j] for j in others}
    first, *rest = others
    total_inv = inv[first]
    prod_u = u[first]
    for n, j in enumerate(rest):
        if n == 0:  # a new array: the rest in place
            total_inv = total_inv + inv[j]
            prod_u = prod_u * u[j]
        else:
            total_inv += inv[j]
            prod_u *= u[j]
    # c_j = (bv + ba2 (inv_j - total_inv)) prod_u / den_j = (ba2 inv_j + base) prod_u / den_j
    base = ba2 * total_inv
    np.subtract(bv, base, out=base)
    # Each difference once; the other order is the same number negated, and the
    # negations of a product are counted instead of applied.
    diff: dict[tuple[int, int], F64 | float] = {}
    for a_, m in enumerate(others):
        for j in others[a_ + 1 :]:
            diff[m, j] = u[m] - u[j]
    acc: F64 | None = None
    for j in others:
        uj = u[j]
        den: F64 | float = 1.0 if isinstance(uj, float) and abs(uj) == 1.0 else uj * uj
        owned = isinstance(den, np.ndarray)  # a fresh array: multiply in place
        negative = False
        for m in others:
            if m != j:
                if (m, j) in diff:
                    d = diff[m, j]
                else:
                    d = diff[j, m]
                    negative = not negative
                if owned:
                    den *= d
                elif isinstance(den, float) and den == 1.0:
                    den = d
                else:
                    den = den * d
                    owned = isinstance(den, np.ndarray)
        if owned and isinstance(den, np.ndarray):
            ratio = np.divide(prod_u, den, out=den)
        else:
            ratio = np.divide(prod_u, den)
        c = ba2 * inv[j]
        c += base
        c *= ratio
        if acc is None:
            if negative:
                np.negative(c, out=c)
            coef[j] += c
            acc = c
        elif negative:
            coef[j] -= c
            acc -= c
        else:
            coef[j] += c
            acc += c
    if acc is not None:
        coef[i] -= acc


def _quintic_basis(s: F64) -> tuple[F64, F64, F64, F64, F64, F64]:
    """Quintic Hermite basis: p0, v0, twice a0, twice a1, v1, p1 (unit interval), by Horner."""
    s2 = s * s
    s3 = s2 * s
    h_p1 = 6.0 * s
    h_p1 -= 15.0
    h_p1 *= s
    h_p1 += 10.0
    h_p1 *= s3  # 10 s^3 - 15 s^4 + 6 s^5
    h_p0 = 1.0 - h_p1
    h_v0 = -3.0 * s
    h_v0 += 8.0
    h_v0 *= s
    h_v0 -= 6.0
    h_v0 *= s3
    h_v0 += s  # s - 6 s^3 + 8 s^4 - 3 s^5
    h_v1 = -3.0 * s
    h_v1 += 7.0
    h_v1 *= s
    h_v1 -= 4.0
    h_v1 *= s3  # -4 s^3 + 7 s^4 - 3 s^5
    h_a0 = 3.0 - s
    h_a0 *= s
    h_a0 -= 3.0
    h_a0 *= s
    h_a0 += 1.0
    h_a0 *= s2  # s^2 - 3 s^3 + 3 s^4 - s^5 (twice the basis function)
    h_a1 = s - 2.0
    h_a1 *= s
    h_a1 += 1.0
    h_a1 *= s3  # s^3 - 2 s^4 + s^5 (twice the basis function)
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
    k = lookbehind + 2 + lookahead
    p = _float_array(keys, "keys", (k, 7))
    batch = p.shape[:-2]
    tt = _checked(times, "times", (k,))
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
    flat = p.reshape(-1, k, 7)
    tflat = tt.reshape(-1, k)
    T = _rows(tflat)
    s, coef = _window_weights(T, q, lookbehind, lookahead)
    out = _window_curve(flat, coef, lookbehind)
    lo, hi = lookbehind, lookbehind + 1
    for mask, j in ((s == 0.0, lo), (s == 1.0, hi)):
        if mask.any():
            out[mask] = flat[mask, j]
    return out.reshape((*batch, 7))


def _window_weights(T: F64, q: F64, lookbehind: int, lookahead: int) -> tuple[F64, F64]:
    """Fractions ``s (M,)`` and the keyframes' weights ``(K, M)`` for window times ``T (K, M)``."""
    lo, hi = lookbehind, lookbehind + 1
    k, m = T.shape
    step = T[1:] - T[:-1]
    if m and step.min() < 0:  # the times are finite
        raise ValueError("expected non-decreasing window `times`")
    span = step[lo]
    held = span <= 0
    any_held = bool(held.any())
    h = np.where(held, 1.0, span) if any_held else span
    s = q - T[lo]
    s /= h
    np.maximum(s, 0.0, out=s)
    np.minimum(s, 1.0, out=s)
    if any_held:
        s[held] = 0.0
    # Node times in spans; a missing neighbour (a repeat outwards of the bracket,
    # or anything after a held one) goes far away, each to its own place. The
    # bracket's nodes are exactly 0 and 1 (a held bracket's upper one is moved to 1).
    x = T - T[lo]
    x /= h
    # Complete windows (the rule, not the exception) skip the substitutions.
    missing: NDArray[np.bool_] = np.any(step <= 0, axis=1)
    gone = held
    any_gone = any_held
    for j in range(hi + 1, k):
        if missing[j - 1]:
            gone = gone | (step[j - 1] <= 0)
            any_gone = True
        if any_gone:
            x[j] = np.where(gone, _FAR * (j - lo), x[j])
    if lo > 0:
        gone = step[lo - 1] <= 0
        for j in range(lo - 1, -1, -1):
            if j < lo - 1:
                gone = gone | (step[j] <= 0)
            if missing[j:lo].any():
                x[j] = np.where(gone, -_FAR * (lo + 1 - j), x[j])
    b_p0, b_v0, b_a0, b_a1, b_v1, b_p1 = _quintic_basis(s)
    # The curve's weight of each keyframe's motor: positions, velocities and
    # accelerations at both ends, each a combination of the keyframes.
    coef = np.zeros((k, m))
    coef[lo] = b_p0
    coef[hi] = b_p1
    xs: list[F64 | float] = list(x)
    xs[lo], xs[hi] = 0.0, 1.0
    _add_derivatives(coef, xs, lo, range(lo - lookbehind, lo + lookahead + 1), b_v0, b_a0)
    _add_derivatives(coef, xs, hi, range(hi - lookbehind, hi + lookahead + 1), b_v1, b_a1)
    return s, coef


def motor_quintic(keys: ArrayLike, times: ArrayLike, t: ArrayLike) -> F64:
    """C2 quintic on motors through a window of 6 keyframes (2 each side), at times ``t``."""
    return motor_window_spline(keys, times, t, QUINTIC_LOOKBEHIND, QUINTIC_LOOKAHEAD)
