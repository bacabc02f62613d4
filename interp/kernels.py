"""Row kernels of the paper's three pair interpolators, without allocations.

A row kernel interpolates pose rows ``A``, ``B`` of shape ``(7, M)`` (component
major; unit quaternions, finite values: the caller validated them) at fractions
``S (M,)`` and writes the poses into ``out (7, M)``, which may be a strided view
(the transpose of an ``(M, 7)`` array). Every intermediate lives in one scratch
array per thread (:func:`scratch`), reused from call to call, and every numpy
operation writes into it with ``out=``: a call allocates nothing that grows
with ``M`` (numpy still takes a few 64 kB iteration buffers for broadcasting
calls on large rows).

Why: freeing and re-allocating a few hundred kB of temporaries per call makes
glibc hand memory back to the OS and page-fault it in again on the next call
(its default mmap and trim thresholds), which halved or thirded throughput
unless the process tuned the allocator (only the ``posecast`` CLI did). With
the scratch reused, throughput no longer depends on how the process started.
At render sizes (100 poses) a numpy call costs 0.3 to 0.6 us whatever it
computes, so the kernels keep their call count low: sums of signed products
(quaternion products, cross products) are one ``take`` of permuted factors and a
few whole-block operations, constants are 0-d arrays, ``out`` is positional,
and the hemisphere alignment can be shared between kernels on the same rows
(:func:`share_rows`, ``shared=``), with motor-lerp's and dq-slerp's common
products.

soa and motor-lerp evaluate the formulas of :mod:`interp.methods`' docstrings
in the order the former expressions did, one ufunc at a time: the same results
bit for bit. dq-slerp is evaluated in the world frame (no vector rotation; see
:func:`dq_slerp_rows`): the same within float rounding (a few 1e-15).

Scratch rows ``0..13`` are left to the caller (:mod:`interp.methods` copies its
chunk of ``a`` and ``b`` there, the receiver the shared alignment); the kernels
use rows ``14`` and up.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import NamedTuple, Protocol

import numpy as np
from numpy.typing import NDArray

from interp.pose import F64

__all__ = [
    "CALLER_ROWS",
    "CHUNK",
    "SCRATCH_ROWS",
    "SHARES_PRODUCTS",
    "RowKernel",
    "Shared",
    "Work",
    "dq_slerp_rows",
    "hemisphere_sign",
    "motor_lerp_rows",
    "scratch",
    "share_rows",
    "soa_rows",
]

#: Poses per kernel call in the batch wrappers: large enough that numpy's per-call
#: overhead is small, small enough that the scratch stays a few MB (64 rows).
CHUNK = 8192
#: Scratch rows reserved for the caller (two chunks of pose rows).
CALLER_ROWS = 14
SCRATCH_ROWS = 64

Work = tuple[F64, NDArray[np.bool_]]
"""Scratch: ``(64, M)`` floats and ``(2, M)`` booleans."""


class RowKernel(Protocol):
    """``kernel(A, B, S, out, work=None, unit_s=False, shared=None, ends=None)``.

    ``A``, ``B`` are ``(7, M)`` rows, ``S`` ``(M,)``, ``out`` ``(7, M)``. ``work`` is
    scratch from :func:`scratch` (default: this thread's); with ``unit_s`` the
    caller promises ``0 <= S <= 1`` (no range check); ``shared`` holds what
    several kernels on the same rows have in common (:func:`share_rows`; read,
    never written); ``ends`` says whether any ``S`` is exactly 0 or 1 (None:
    look), where the keyframes are copied to the output bit for bit.
    """

    def __call__(
        self,
        A: F64,
        B: F64,
        S: F64,
        out: F64,
        work: Work | None = None,
        unit_s: bool = False,
        shared: Shared | None = None,
        ends: bool | None = None,
    ) -> None: ...


# Constants as 0-d arrays: a Python float operand costs a conversion per call.
_ZERO, _HALF, _ONE, _TWO = (np.array(x) for x in (0.0, 0.5, 1.0, 2.0))
_HALF_PI = 0.5 * np.pi

# Local names and positional ``out``: at render sizes the call overhead is the cost.
_mul, _add, _sub, _div = np.multiply, np.add, np.subtract, np.divide
_sqrt, _atan2, _tan, _copysign, _eq = np.sqrt, np.arctan2, np.tan, np.copysign, np.equal
_sin, _cos, _negative = np.sin, np.cos, np.negative
#: ``reduce(array, axis, dtype, out)``: numpy's stubs only type ``out`` as a keyword.
_add_reduce: Callable[..., F64] = np.add.reduce

_local = threading.local()


def scratch(m: int) -> Work:
    """This thread's scratch for ``m`` columns: contiguous ``(64, m)`` floats and
    ``(2, m)`` booleans, views of one buffer kept per thread.

    Every width gets contiguous rows and blocks (what ``take`` with ``out=`` and
    ``reshape`` need to stay allocation-free). The buffer grows when ``m`` needs
    more, never shrinks, and is not zeroed: every kernel writes before it reads.
    """
    last: tuple[int, Work] | None = getattr(_local, "last", None)
    if last is not None and last[0] == m:  # the render frame asks for the same width
        return last[1]
    flat: F64 | None = getattr(_local, "flat", None)
    need = SCRATCH_ROWS * m
    if flat is None or flat.shape[0] < need:
        size = max(need, 0 if flat is None else min(2 * flat.shape[0], SCRATCH_ROWS * CHUNK))
        flat = np.empty(size)
        _local.flat = flat
        _local.flags = np.empty(2 * (size // SCRATCH_ROWS), dtype=bool)
    flags: NDArray[np.bool_] = _local.flags
    work = (flat[:need].reshape(SCRATCH_ROWS, m), flags[: 2 * m].reshape(2, m))
    _local.last = (m, work)
    return work


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


def _align(q0: F64, b: F64, q1: F64, dot: F64, t4: F64) -> None:
    """``q1`` <- ``b`` in ``q0``'s hemisphere; ``dot`` <- ``q0.q1 >= 0``."""
    _mul(q0, b, t4)
    _add_reduce(t4, 0, None, dot)
    sign = t4[0]
    if np.count_nonzero(dot) == dot.shape[0]:  # no exact half turn: the dot's sign decides
        _copysign(_ONE, dot, sign)
    else:
        sign = hemisphere_sign(q0, b, dot)
    _mul(b, sign, q1)
    _mul(dot, sign, dot)


class Shared(NamedTuple):
    """What several kernels on the same rows ``A``, ``B``, ``S`` have in common,
    computed once by :func:`share_rows`. Kernels read it and write none of it."""

    #: ``B``'s quaternions in ``A``'s hemisphere, and ``q0.q1 >= 0``.
    q1: F64
    dot: F64
    #: ``1 - S``.
    r: F64
    #: The vector part of ``q0 q1*`` (motor-lerp's ``c``; minus ScLERP's screw axis
    #: ``vec(q1 q0*)``) and ``(t0 - t1) x cv`` (minus ScLERP's ``v x (t1 - t0)``).
    cv: F64 | None = None
    cross: F64 | None = None


def share_rows(A: F64, B: F64, S: F64, products: bool = False) -> Shared:
    """The hemisphere alignment and ``1 - S`` of these rows, and with ``products`` the
    products motor-lerp and dq-slerp both need (:class:`Shared`), in a new small array.

    Meant for a render frame with several methods (a few hundred poses at most).
    """
    m = S.shape[0]
    own = np.empty((15 if products else 6, m))
    w, _ = scratch(m)
    q1, dot, r = own[0:4], own[4], own[5]
    _align(A[3:], B[3:], q1, dot, w[14:18])
    _sub(_ONE, S, r)
    if not products:
        return Shared(q1, dot, r)
    cv, u3, cross = own[6:9], own[9:12], own[12:15]
    _products(A[3:], q1, _C_VEC, cv, w[14:26])
    _sub(A[:3], B[:3], u3)
    _cross(u3, cv, cross, w[14:26])
    return Shared(q1, dot, r, cv, cross)


def _sincos(
    x: F64, sin: F64, cos: F64, t: F64, t2: F64, check: bool, half: F64 | None = None
) -> None:
    """sin and cos of angles in ``[0, pi/2]`` through ``t = tan(x/2)``.

    This numpy's float64 sin and cos are scalar loops while tan is vectorised;
    with ``t <= 1`` the half-angle forms are accurate to an ulp. Outside that
    range (extrapolation; ``check`` looks for it) the plain functions are used.
    ``half``, if given, is ``x / 2`` already (then ``x`` is only read by the check).
    """
    if check and x.shape[0] and (np.minimum.reduce(x) < 0.0 or np.maximum.reduce(x) > _HALF_PI):
        _sin(x, sin)
        _cos(x, cos)
        return
    if half is None:
        _mul(x, _HALF, t)
        _tan(t, t)
    else:
        _tan(half, t)
    _mul(t, t, t2)
    inv = cos  # 1 / (1 + t^2), until cos is written
    _add(t2, _ONE, inv)
    _div(_ONE, inv, inv)
    _mul(t, _TWO, sin)
    _mul(sin, inv, sin)
    _sub(_ONE, t2, t2)
    _mul(t2, inv, cos)


def _divisor(den: F64, zero: NDArray[np.bool_], into: F64) -> tuple[F64, bool]:
    """``den`` with its exact zeros replaced by 1 (in ``into`` if there are any), and
    whether there were: a zero angle's ratio then takes its limit (:func:`_ratio`)."""
    _eq(den, _ZERO, zero)
    if not np.count_nonzero(zero):
        return den, False
    np.copyto(into, den)
    np.copyto(into, _ONE, where=zero)
    return into, True


def _ratio(num: F64, den: F64, limit: F64, into: F64, zero: NDArray[np.bool_], any0: bool) -> None:
    """``into`` <- ``num / den``, or ``limit`` where the divisor was zero."""
    _div(num, den, into)
    if any0:
        np.copyto(into, limit, where=zero)


def _exact_ends(
    out: F64,
    A: F64,
    B: F64,
    S: F64,
    r: F64,
    at: NDArray[np.bool_],
    t: F64,
    ends: bool | None,
) -> None:
    """s = 0 and s = 1 give the keyframes bit for bit (``r = 1 - s``; ``t``: scratch).

    ``s (1 - s) == 0`` exactly when ``s`` is 0 or 1 (no product of these
    underflows); ``ends`` is the caller's answer to that, if it knows.
    """
    if ends is None:
        _mul(S, r, t)
        _eq(t, _ZERO, at)
        ends = bool(np.count_nonzero(at))
    if not ends:
        return
    _eq(S, _ZERO, at)
    if np.count_nonzero(at):
        np.copyto(out, A, where=at)
    _eq(S, _ONE, at)
    if np.count_nonzero(at):
        np.copyto(out, B, where=at)


def soa_rows(
    A: F64,
    B: F64,
    S: F64,
    out: F64,
    work: Work | None = None,
    unit_s: bool = False,
    shared: Shared | None = None,
    ends: bool | None = None,
) -> None:
    """Position LERP + quaternion SLERP (the formulas of :func:`interp.methods.soa`)."""
    m = S.shape[0]
    w, mask = scratch(m) if work is None else work
    q0, q1, dm, nn = A[3:], w[14:18], w[18:26], w[26:28]
    dot, sin_w, sw, r, c0, c1, t, t2, den = w[28:37]
    if shared is None:
        _align(q0, B[3:], q1, dot, dm[:4])
        _sub(_ONE, S, r)
    else:
        q1, dot, r = shared.q1, shared.dot, shared.r
    # Half chords d = q1 - q0 and m = q1 + q0 and their norms, in one block.
    _sub(q1, q0, dm[:4])
    _add(q1, q0, dm[4:])
    _mul(dm, dm, dm)
    _add_reduce(dm.reshape(2, 4, m), 1, None, nn)
    _sqrt(nn, nn)
    nd, nm = nn
    _mul(nd, _HALF, sin_w)
    _mul(sin_w, nm, sin_w)
    # s w = s 2 atan2(nd, nm); its half, s atan2(nd, nm), is the same bits over 2.
    _atan2(nd, nm, c0)
    _mul(S, c0, c0)
    if not unit_s:
        _mul(c0, _TWO, sw)
    sin_sw, cos_sw = nd, nm
    _sincos(sw, sin_sw, cos_sw, t, t2, check=not unit_s, half=c0)
    # c0 = (sin w cos sw - cos w sin sw) / sin w, limit 1 - s; c1 = sin sw / sin w, limit s.
    zero = mask[0]
    div, any0 = _divisor(sin_w, zero, den)
    _mul(sin_w, cos_sw, t)
    _mul(dot, sin_sw, t2)
    _sub(t, t2, t)
    _ratio(t, div, r, c0, zero, any0)
    _ratio(sin_sw, div, S, c1, zero, any0)
    p3, t4 = dm[:3], dm[4:]
    _sub(B[:3], A[:3], p3)
    _mul(S, p3, p3)
    _add(A[:3], p3, out[:3])
    _mul(c0, q0, t4)
    _mul(c1, q1, dm[:4])
    _add(t4, dm[:4], out[3:])
    _exact_ends(out, A, B, S, r, mask[1], t, ends)


def motor_lerp_rows(
    A: F64,
    B: F64,
    S: F64,
    out: F64,
    work: Work | None = None,
    unit_s: bool = False,
    shared: Shared | None = None,
    ends: bool | None = None,
) -> None:
    """Motor LERP with Study normalisation (:func:`interp.methods.motor_lerp`).

    ``unit_s`` changes nothing here (no trig); it is accepted for the common signature.
    """
    w, mask = scratch(S.shape[0]) if work is None else work
    t0, q0, t1 = A[:3], A[3:], B[:3]
    q1, t4, cv, u3, v3 = w[14:18], w[18:22], w[22:25], w[25:28], w[28:31]
    dot, r, rr, ss, rs, x, y = w[31:38]
    buf, z3 = w[38:50], w[50:53]
    if shared is None:
        _align(q0, B[3:], q1, dot, t4)
        _sub(_ONE, S, r)
    else:
        q1, dot, r = shared.q1, shared.dot, shared.r
    if shared is not None and shared.cv is not None and shared.cross is not None:
        cv, cross = shared.cv, shared.cross
    else:
        _products(q0, q1, _C_VEC, cv, buf)  # vector part of c = q0 q1*
        _sub(t0, t1, u3)
        _cross(u3, cv, v3, buf)
        cross = v3
    _mul(r, r, rr)
    _mul(S, S, ss)
    _mul(r, S, rs)
    # num = rr t0 + ss t1 + rs (dot (t0 + t1) + (t0 - t1) x cv)
    _add(t0, t1, u3)
    _mul(dot, u3, u3)
    _add(u3, cross, u3)
    _mul(rs, u3, u3)
    _mul(rr, t0, v3)
    _mul(ss, t1, z3)
    _add(v3, z3, v3)
    _add(v3, u3, v3)
    # den = rr + ss + 2 rs dot
    _add(rr, ss, x)
    _mul(rs, _TWO, y)
    _mul(y, dot, y)
    _add(x, y, x)
    _div(v3, x, out[:3])
    # Rotation: the normalised quaternion blend r q0 + s q1.
    qs = buf[:4]
    _mul(r, q0, t4)
    _mul(S, q1, qs)
    _add(t4, qs, t4)
    _mul(t4, t4, qs)
    _add_reduce(qs, 0, None, x)
    _sqrt(x, x)
    _div(t4, x, out[3:])
    _exact_ends(out, A, B, S, r, mask[1], x, ends)


def dq_slerp_rows(
    A: F64,
    B: F64,
    S: F64,
    out: F64,
    work: Work | None = None,
    unit_s: bool = False,
    shared: Shared | None = None,
    ends: bool | None = None,
) -> None:
    """Dual-quaternion ScLERP on the screw (:func:`interp.methods.dq_slerp`).

    Evaluated in the world frame: with ``D = t1 - t0`` and the relative rotation
    ``q1 q0* = (cos phi, v)`` (``v = sin(phi) u``, the screw axis in world
    coordinates; ``R0`` maps ``methods``' body-frame ``t_d``, ``u``, ``v x t_d`` to
    ``D``, ``u``, ``v x D``), ``t = t0 + kc D + (s - kc) (D.u) u - k kr (v x D)``;
    the rotation ``q0 (cos s phi, k v_body)`` equals ``kr q0 + k q1`` (SLERP).
    No rotation of a vector is needed.
    """
    w, mask = scratch(S.shape[0]) if work is None else work
    t0, q0 = A[:3], A[3:]
    q1, t4, v, d, u, t3 = w[14:18], w[18:22], w[22:25], w[25:28], w[28:31], w[31:34]
    cos_phi, sin_phi, sphi, sin_s, cos_s, sin_r, r, k, kr, x, y, den = w[34:46]
    buf = w[46:58]
    if shared is None:
        _align(q0, B[3:], q1, cos_phi, t4)
        _sub(_ONE, S, r)
    else:
        q1, cos_phi, r = shared.q1, shared.dot, shared.r
    if shared is not None and shared.cv is not None:
        _negative(shared.cv, v)  # vector part of q1 q0*: minus that of q0 q1*
    else:
        _products(q0, q1, _REL_VEC_WORLD, v, buf)
    _mul(v, v, t3)
    _add_reduce(t3, 0, None, sin_phi)
    _sqrt(sin_phi, sin_phi)
    _atan2(sin_phi, cos_phi, sphi)  # phi in [0, pi/2]: cos_phi >= 0
    _mul(S, sphi, sphi)
    _sincos(sphi, sin_s, cos_s, x, y, check=not unit_s)
    # (1-s) phi by angle addition: no further trig calls.
    cos_r = sphi
    _mul(sin_phi, cos_s, sin_r)
    _mul(cos_phi, sin_s, x)
    _sub(sin_r, x, sin_r)
    _mul(cos_phi, cos_s, cos_r)
    _mul(sin_phi, sin_s, x)
    _add(cos_r, x, cos_r)
    zero = mask[0]
    div, any0 = _divisor(sin_phi, zero, den)
    _ratio(sin_s, div, S, k, zero, any0)  # sin(s phi) / sin(phi), limit s
    _ratio(sin_r, div, r, kr, zero, any0)  # sin((1-s) phi) / sin(phi), limit 1 - s
    kc = cos_r
    _mul(k, cos_r, kc)
    _sub(B[:3], t0, d)
    # Unit axis, or 0 without rotation (the along-axis term then has weight 0).
    _div(v, div, u)
    along = y
    _mul(d, u, t3)
    _add_reduce(t3, 0, None, along)
    _sub(S, kc, x)
    _mul(x, along, along)
    # t = t0 + kc D + along u - (k kr) (v x D)
    if shared is not None and shared.cross is not None:
        _negative(shared.cross, t3)  # v x D = (-cv) x (t1 - t0) = -((t0 - t1) x cv)
    else:
        _cross(v, d, t3, buf)
    _mul(k, kr, x)
    _mul(x, t3, t3)
    _mul(kc, d, d)
    _mul(along, u, u)
    _add(d, u, d)
    _sub(d, t3, d)
    _add(t0, d, out[:3])
    # q = kr q0 + k q1
    _mul(kr, q0, t4)
    _mul(k, q1, buf[:4])
    _add(t4, buf[:4], out[3:])
    _exact_ends(out, A, B, S, r, mask[1], x, ends)


def _table(rows: list[list[tuple[int, int]]]) -> tuple[NDArray[np.intp], F64]:
    """``(perm, sign)`` of a sum-of-products table: ``rows[j][i] = (k, +-1)``."""
    perm = np.array([[k for k, _ in r] for r in rows], dtype=np.intp).reshape(-1)
    sign = np.array([[g for _, g in r] for r in rows], dtype=np.float64).reshape(-1, 1)
    return perm, sign


# out[i] = sum over j (in order) of sign * p[j] * q[k], (k, sign) = TABLE[j][i].
# Each is the order in which the reference formula sums its terms; a negated
# term added is the same as subtracting it, bit for bit.
#: Vector part of q0 q1* (motor LERP's c).
_C_VEC = _table(
    [
        [(1, -1), (2, -1), (3, -1)],
        [(0, 1), (3, 1), (2, -1)],
        [(3, -1), (0, 1), (1, 1)],
        [(2, 1), (1, -1), (0, 1)],
    ]
)
#: Vector part of q1 q0* (ScLERP's screw axis in world coordinates): minus that of q0 q1*.
_REL_VEC_WORLD = (_C_VEC[0], -_C_VEC[1])
#: u x v: [u1 u2 u0 u2 u0 u1] * [v2 v0 v1 v1 v2 v0], first half minus second.
_CROSS_U = np.array([1, 2, 0, 2, 0, 1], dtype=np.intp)
_CROSS_V = np.array([2, 0, 1, 1, 2, 0], dtype=np.intp)


def _products(p: F64, q: F64, table: tuple[NDArray[np.intp], F64], out: F64, buf: F64) -> None:
    """``out (k, M)`` <- the signed sum of products ``table`` of rows ``p (4, M)``
    and ``q``, summed left to right (``buf``: ``4 k`` scratch rows)."""
    perm, sign = table
    k, m = out.shape
    terms = buf[: 4 * k]
    q.take(perm, 0, terms, "clip")  # the method: np.take adds a Python wrapper
    _mul(terms, sign, terms)
    blocks = terms.reshape(4, k, m)
    _mul(blocks, p[:, None, :], blocks)
    _add(blocks[0], blocks[1], out)
    _add(out, blocks[2], out)
    _add(out, blocks[3], out)


def _cross(u: F64, v: F64, out: F64, buf: F64) -> None:
    """``out`` <- ``u x v`` for vector rows ``(3, M)`` (``buf``: 12 scratch rows)."""
    a, b = buf[:6], buf[6:12]
    u.take(_CROSS_U, 0, a, "clip")
    v.take(_CROSS_V, 0, b, "clip")
    _mul(a, b, a)
    _sub(a[:3], a[3:], out)


#: The kernels that read :attr:`Shared.cv` and :attr:`Shared.cross`: worth computing
#: (``share_rows(..., products=True)``) when two of them run on the same rows.
SHARES_PRODUCTS: frozenset[RowKernel] = frozenset({motor_lerp_rows, dq_slerp_rows})
