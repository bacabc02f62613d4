"""Building blocks of the row kernels (:mod:`interp.kernels`): the per-thread
scratch, cached views of it, and the few operations the kernels share.

Every function here writes into arrays it is given (``out=`` everywhere) and
allocates nothing that grows with the number of poses. At render sizes (100
poses) a numpy call costs 0.3 to 0.6 us whatever it computes, so:

- views of the scratch are built once per scratch array and kept
  (:func:`cached_views`), and so are the views of the last rows ``A``, ``B``
  (:func:`end_views`): slicing costs 0.1 us a view, and a kernel uses thirty;
- no ufunc broadcasts a row over a block on narrow rows (about 1 us against
  0.35 for equal shapes): a per-pose factor is first repeated into a block
  (:func:`repeated`, or one ``take`` with :data:`X8` / :data:`X9` for several);
  on wide rows (over :data:`NARROW` poses) broadcasting is free and a copy
  would cost a pass over memory, so there the factor broadcasts;
- sums of signed products (quaternion and cross products) are one ``take`` of
  permuted, signed factors from ``[q; -q]``, one of the other factors, one
  product and whole-block additions (:func:`signed_products`); sums over the
  rows of a block are row additions, in the order ``add.reduce`` sums them.

The order of every product and sum is the one of the formulas in
:mod:`interp.methods`' docstrings, so the results do not change with these
choices (a negated term added is the same as subtracting it, bit for bit).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import NamedTuple, TypeVar, cast

import numpy as np
from numpy.typing import NDArray

from posecast.interp.pose import F64

__all__ = [
    "CALLER_ROWS",
    "CHUNK",
    "C_VEC",
    "NARROW",
    "REL_VEC_WORLD",
    "SCRATCH_ROWS",
    "X8",
    "X9",
    "Align",
    "Cross",
    "Dot3",
    "Products",
    "Work",
    "align_rows",
    "align_views",
    "cached_views",
    "cross_rows",
    "cross_views",
    "dot3",
    "dot3_views",
    "end_views",
    "exact_ends",
    "hemisphere_sign",
    "nonzero_divisor",
    "products_views",
    "ratio_or_limit",
    "repeated",
    "scratch",
    "signed_products",
    "sincos_rows",
]

#: Poses per kernel call in the batch wrappers: large enough that numpy's per-call
#: overhead is small, small enough that the scratch stays a few MB (80 rows).
CHUNK = 8192
#: Scratch rows reserved for the caller (two chunks of pose rows).
CALLER_ROWS = 14
SCRATCH_ROWS = 80

Work = tuple[F64, NDArray[np.bool_]]
"""Scratch: ``(80, M)`` floats and ``(2, M)`` booleans."""


#: Constants as 0-d arrays: a Python float operand costs a conversion per call.
ZERO, HALF, ONE, TWO = (np.array(x) for x in (0.0, 0.5, 1.0, 2.0))
HALF_PI = 0.5 * np.pi

# Local names and positional ``out``: at render sizes the call overhead is the cost.
_mul, _add, _sub, _div = np.multiply, np.add, np.subtract, np.divide
_sqrt, _atan2, _tan, _copysign, _eq = np.sqrt, np.arctan2, np.tan, np.copysign, np.equal
_sin, _cos, _negative, _copyto = np.sin, np.cos, np.negative, np.copyto
_count = np.count_nonzero

_local = threading.local()
_V = TypeVar("_V")


def scratch(m: int) -> Work:
    """This thread's scratch for ``m`` columns: contiguous ``(80, m)`` floats and
    ``(2, m)`` booleans, views of one buffer kept per thread.

    Every width gets contiguous rows and blocks (what ``take`` with ``out=`` and
    ``reshape`` need to stay allocation-free). The buffer grows when ``m`` needs
    more, never shrinks, and is not zeroed: every kernel writes before it reads.
    The views are kept for the last few widths (a batch alternates between full
    chunks and its last one; a render frame asks for the same width every time).
    """
    works: dict[int, Work] | None = getattr(_local, "works", None)
    if works is not None and (work := works.get(m)) is not None:
        return work
    flat: F64 | None = getattr(_local, "flat", None)
    need = SCRATCH_ROWS * m
    if flat is None or flat.shape[0] < need:
        size = max(need, 0 if flat is None else min(2 * flat.shape[0], SCRATCH_ROWS * CHUNK))
        flat = np.empty(size)
        _local.flat = flat
        _local.flags = np.empty(2 * (size // SCRATCH_ROWS), dtype=bool)
        works = None  # views of the former buffer: let it go
    if works is None or len(works) >= 8:
        works = _local.works = {}
    flags: NDArray[np.bool_] = _local.flags
    work = (flat[:need].reshape(SCRATCH_ROWS, m), flags[: 2 * m].reshape(2, m))
    works[m] = work
    return work


def cached_views(work: Work, build: Callable[[F64, NDArray[np.bool_]], _V]) -> _V:
    """``build(*work)``: a kernel's named views of the scratch, kept per thread and
    width for the last scratch array of that width (:func:`scratch` keeps those)."""
    cache: dict[tuple[object, int], tuple[F64, object]] | None = getattr(_local, "views", None)
    if cache is None or len(cache) >= 64:
        cache = _local.views = {}
    key = (build, work[0].shape[1])
    hit = cache.get(key)
    if hit is not None and hit[0] is work[0]:
        return cast(_V, hit[1])
    views = build(*work)
    cache[key] = (work[0], views)
    return views


def end_views(A: F64, B: F64) -> tuple[F64, F64, F64, F64]:
    """``(A[:3], A[3:], B[:3], B[3:])``, kept for the last rows ``A``, ``B`` of this
    thread (several kernels, or the same one frame after frame, on the same rows)."""
    last: tuple[F64, F64, tuple[F64, F64, F64, F64]] | None = getattr(_local, "ends", None)
    if last is not None and last[0] is A and last[1] is B:
        return last[2]
    views = (A[:3], A[3:], B[:3], B[3:])
    _local.ends = (A, B, views)
    return views


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


#: Up to this many columns a per-pose factor is repeated into a block before it
#: multiplies one (an equal-shape ufunc call costs a third of a broadcasting one
#: at render sizes); beyond, it broadcasts (a copy would cost a pass over memory).
NARROW = 1024


def repeated(row: F64, block: F64, narrow: bool) -> F64:
    """``row (M,)`` as the factor of a ``(k, M)`` block: copied into ``block`` when
    narrow, the row itself (to broadcast) when wide."""
    if narrow:
        _copyto(block, row)
        return block
    return row


class Align(NamedTuple):
    """Scratch of :func:`align_rows`: a ``(4, M)`` block and its rows."""

    t4: F64
    rows: tuple[F64, F64, F64, F64]
    narrow: bool


def align_views(t4: F64) -> Align:
    return Align(t4, (t4[0], t4[1], t4[2], t4[3]), t4.shape[1] <= NARROW)


def align_rows(q0: F64, b: F64, q1: F64, dot: F64, s: Align) -> None:
    """``q1`` <- ``b`` in ``q0``'s hemisphere; ``dot`` <- ``q0.q1 >= 0``."""
    t4, (p0, p1, p2, p3), narrow = s
    _mul(q0, b, t4)
    _add(p0, p1, dot)
    _add(dot, p2, dot)
    _add(dot, p3, dot)
    sign = t4 if narrow else p0
    if _count(dot) == dot.shape[0]:  # no exact half turn: the dot's sign decides
        _copysign(ONE, repeated(dot, t4, narrow), sign)
    else:
        _copyto(sign, hemisphere_sign(q0, b, dot))
    _mul(b, sign, q1)
    _mul(dot, p0, dot)


def product_table(rows: list[list[tuple[int, int]]]) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Indices of a sum of products: ``rows[j][i] = (k, +-1)`` says that term ``j`` of
    ``out[i]`` is ``+-q[k] p[j]``. Returns where to take each signed ``q`` factor in
    ``[q; -q]`` and each ``p`` factor, block ``j`` after block ``j``."""
    qq = np.array([[k + (4 if g < 0 else 0) for k, g in r] for r in rows], dtype=np.intp)
    pp = np.array([[j] * len(r) for j, r in enumerate(rows)], dtype=np.intp)
    return qq.reshape(-1), pp.reshape(-1)


# out[i] = sum over j (in order) of sign * q[k] * p[j], (k, sign) = TABLE[j][i].
# Each is the order in which the reference formula sums its terms; a negated
# term added is the same as subtracting it, bit for bit.
C_ROWS = [
    [(1, -1), (2, -1), (3, -1)],
    [(0, 1), (3, 1), (2, -1)],
    [(3, -1), (0, 1), (1, 1)],
    [(2, 1), (1, -1), (0, 1)],
]
#: Vector part of q0 q1* (motor LERP's c).
C_VEC = product_table(C_ROWS)
#: Vector part of q1 q0* (ScLERP's screw axis in world coordinates): minus that of q0 q1*.
REL_VEC_WORLD = product_table([[(k, -g) for k, g in r] for r in C_ROWS])
#: u x v: [u1 u2 u0 u2 u0 u1] * [v2 v0 v1 v1 v2 v0], first half minus second.
CROSS_U = np.array([1, 2, 0, 2, 0, 1], dtype=np.intp)
CROSS_V = np.array([2, 0, 1, 1, 2, 0], dtype=np.intp)
#: Repeat rows of a block: 2 rows to 2 x 4, 3 rows to 3 x 3.
X8 = np.array([0, 0, 0, 0, 1, 1, 1, 1], dtype=np.intp)
X9 = np.array([0, 0, 0, 1, 1, 1, 2, 2, 2], dtype=np.intp)


class Products(NamedTuple):
    """Scratch of :func:`signed_products`: ``[q; -q]`` (whose first half the caller fills),
    the ``(12, M)`` signed ``q`` factors as four ``(3, M)`` blocks, the ``p`` factors."""

    qq: F64
    neg: F64
    terms: F64
    blocks: tuple[F64, F64, F64, F64]
    pterms: F64


def products_views(qq: F64, terms: F64, pterms: F64) -> Products:
    b = terms.reshape(4, 3, terms.shape[1])
    return Products(qq, qq[4:], terms, (b[0], b[1], b[2], b[3]), pterms)


def signed_products(
    p: F64, q: F64, table: tuple[NDArray[np.intp], NDArray[np.intp]], out: F64, s: Products
) -> None:
    """``out (3, M)`` <- the signed sum of products ``table`` of rows ``p (4, M)`` and
    ``q`` (``s.qq[:4]``, where the caller put it), summed left to right."""
    qq, neg, terms, (b0, b1, b2, b3), pterms = s
    _negative(q, neg)
    qq.take(table[0], 0, terms, "clip")  # the method: np.take adds a Python wrapper
    p.take(table[1], 0, pterms, "clip")
    _mul(terms, pterms, terms)
    _add(b0, b1, out)
    _add(out, b2, out)
    _add(out, b3, out)


class Dot3(NamedTuple):
    """Scratch of :func:`dot3`: a ``(3, M)`` block and its rows."""

    prod: F64
    rows: tuple[F64, F64, F64]


def dot3_views(prod: F64) -> Dot3:
    return Dot3(prod, (prod[0], prod[1], prod[2]))


def dot3(u: F64, v: F64, s: Dot3, out: F64) -> None:
    """``out`` <- ``u . v`` for vector rows ``(3, M)``, summed left to right."""
    prod, (p0, p1, p2) = s
    _mul(u, v, prod)
    _add(p0, p1, out)
    _add(out, p2, out)


class Cross(NamedTuple):
    """Scratch of :func:`cross_rows`: 12 rows and their halves."""

    a: F64
    b: F64
    a_hi: F64
    a_lo: F64


def cross_views(buf: F64) -> Cross:
    a = buf[:6]
    return Cross(a, buf[6:12], a[:3], a[3:])


def cross_rows(u: F64, v: F64, out: F64, s: Cross) -> None:
    """``out`` <- ``u x v`` for vector rows ``(3, M)``."""
    a, b, hi, lo = s
    u.take(CROSS_U, 0, a, "clip")
    v.take(CROSS_V, 0, b, "clip")
    _mul(a, b, a)
    _sub(hi, lo, out)


def sincos_rows(
    x: F64, sin: F64, cos: F64, t: F64, t2: F64, check: bool, half: F64 | None = None
) -> None:
    """sin and cos of angles in ``[0, pi/2]`` through ``t = tan(x/2)``.

    This numpy's float64 sin and cos are scalar loops while tan is vectorised;
    with ``t <= 1`` the half-angle forms are accurate to an ulp. Outside that
    range (extrapolation; ``check`` looks for it) the plain functions are used.
    ``half``, if given, is ``x / 2`` already (then ``x`` is only read by the check).
    """
    if check and x.shape[0] and (np.minimum.reduce(x) < 0.0 or np.maximum.reduce(x) > HALF_PI):
        _sin(x, sin)
        _cos(x, cos)
        return
    if half is None:
        _mul(x, HALF, t)
        _tan(t, t)
    else:
        _tan(half, t)
    _mul(t, t, t2)
    inv = cos  # 1 / (1 + t^2), until cos is written
    _add(t2, ONE, inv)
    _div(ONE, inv, inv)
    _mul(t, TWO, sin)
    _mul(sin, inv, sin)
    _sub(ONE, t2, t2)
    _mul(t2, inv, cos)


def nonzero_divisor(den: F64, zero: NDArray[np.bool_], into: F64) -> tuple[F64, bool]:
    """``den`` with its exact zeros replaced by 1 (in ``into`` if there are any), and
    whether there were: a zero angle's ratio then takes its limit (:func:`ratio_or_limit`)."""
    if _count(den) == den.shape[0]:
        return den, False
    _eq(den, ZERO, zero)
    _copyto(into, den)
    _copyto(into, ONE, where=zero)
    return into, True


def ratio_or_limit(
    num: F64, den: F64, limit: F64, into: F64, zero: NDArray[np.bool_], any0: bool
) -> None:
    """``into`` <- ``num / den``, or ``limit`` where the divisor was zero."""
    _div(num, den, into)
    if any0:
        _copyto(into, limit, where=zero)


def exact_ends(
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
        ends = _count(t) < t.shape[0]
    if not ends:
        return
    _eq(S, ZERO, at)
    if _count(at):
        _copyto(out, A, where=at)
    _eq(S, ONE, at)
    if _count(at):
        _copyto(out, B, where=at)
