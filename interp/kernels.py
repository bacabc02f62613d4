"""Row kernels of the paper's three pair interpolators, without allocations.

A row kernel interpolates pose rows ``A``, ``B`` of shape ``(7, M)`` (component
major; unit quaternions, finite values: the caller validated them) at fractions
``S (M,)`` and writes the poses into ``out (7, M)``, which may be a strided view
(the transpose of an ``(M, 7)`` array). Every intermediate lives in one scratch
array per thread (:func:`scratch`), reused from call to call, and every numpy
operation writes into it with ``out=``: a call allocates nothing that grows
with ``M``.

Why: freeing and re-allocating a few hundred kB of temporaries per call makes
glibc hand memory back to the OS and page-fault it in again on the next call
(its default mmap and trim thresholds), which halved or thirded throughput
unless the process tuned the allocator (only the ``posecast`` CLI did). With
the scratch reused, throughput no longer depends on how the process started.
At render sizes (100 poses) the cost is the number of numpy calls and the
Python around them: :mod:`interp.rowops` says how the kernels keep both low.
Several kernels on the same rows can share the hemisphere alignment and
motor-lerp's and dq-slerp's common products (:func:`share_rows`, ``shared=``).

soa and motor-lerp evaluate the formulas of :mod:`interp.methods`' docstrings
in the order the former expressions did, one ufunc at a time: the same results
bit for bit. dq-slerp is evaluated in the world frame (no vector rotation; see
:func:`dq_slerp_rows`): the same within float rounding (a few 1e-15).

Scratch rows ``0..13`` are left to the caller (:mod:`interp.methods` copies its
chunk of ``a`` and ``b`` there); the kernels use rows ``14`` and up.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple, Protocol

import numpy as np
from numpy.typing import NDArray

from posecast.interp.pose import F64
from posecast.interp.rowops import (
    C_VEC,
    CALLER_ROWS,
    CHUNK,
    HALF,
    NARROW,
    ONE,
    REL_VEC_WORLD,
    SCRATCH_ROWS,
    TWO,
    X8,
    X9,
    Align,
    Cross,
    Dot3,
    Products,
    Work,
    align_rows,
    align_views,
    cached_views,
    cross_rows,
    cross_views,
    dot3,
    dot3_views,
    end_views,
    exact_ends,
    hemisphere_sign,
    nonzero_divisor,
    products_views,
    ratio_or_limit,
    repeated,
    scratch,
    signed_products,
    sincos_rows,
)

__all__ = [
    "CALLER_ROWS",
    "CHUNK",
    "COMPILED_KIND",
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

# Local names and positional ``out``: at render sizes the call overhead is the cost.
_mul, _add, _sub, _div = np.multiply, np.add, np.subtract, np.divide
_sqrt, _atan2, _negative, _copyto = np.sqrt, np.arctan2, np.negative, np.copyto
#: ``reduce(array, axis, dtype, out)``: numpy's stubs only type ``out`` as a keyword.
_add_reduce: Callable[..., F64] = np.add.reduce


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


class _ShareViews(NamedTuple):
    """:func:`share_rows`' views: its own array (the result) and scratch."""

    own: F64
    shared: Shared
    align: Align
    products: Products
    u3: F64
    cross: Cross


def _share_views(w: F64, _: NDArray[np.bool_]) -> _ShareViews:
    m = w.shape[1]
    own = np.empty((16, m))
    return _ShareViews(
        own,
        Shared(own[0:4], own[8], own[9], own[10:13], own[13:16]),
        align_views(w[14:18]),
        products_views(own[0:8], w[18:30], w[30:42]),
        w[42:45],
        cross_views(w[18:30]),
    )


def share_rows(A: F64, B: F64, S: F64, products: bool = False) -> Shared:
    """The hemisphere alignment and ``1 - S`` of these rows, and with ``products`` the
    products motor-lerp and dq-slerp both need (:class:`Shared`).

    Meant for a render frame with several methods (a few hundred poses at most).
    The result lives in an array of this thread's, valid until the next call.
    """
    v = cached_views(scratch(S.shape[0]), _share_views)
    t0, q0, t1, b = end_views(A, B)
    shared = v.shared
    q1, dot, r, cv, cross = shared
    assert cv is not None and cross is not None
    align_rows(q0, b, q1, dot, v.align)
    _sub(ONE, S, r)
    if not products:
        return Shared(q1, dot, r)
    signed_products(q0, q1, C_VEC, cv, v.products)
    u3 = v.u3
    _sub(t0, t1, u3)
    cross_rows(u3, cv, cross, v.cross)
    return shared


class _SoaViews(NamedTuple):
    """:func:`soa_rows`' views of a scratch (:func:`interp.rowops.cached_views`)."""

    q1: F64
    align: Align
    dm: F64
    d: F64
    m: F64
    dm_sums: F64  # dm as (2, 4, M)
    nn: F64
    nd: F64
    nm: F64
    cc: F64  # the weights c0, c1 of q0 and q1
    c0: F64
    c1: F64
    c8: F64  # cc repeated (narrow): c0 x 4, c1 x 4
    c8_0: F64  # the factors of q0 and q1: c8's halves, or (wide) c0 and c1
    c8_1: F64
    prod: F64  # c0 q0 and c1 q1
    prod1: F64
    s3: F64  # S repeated x 3
    p3: F64
    dot: F64
    sin_w: F64
    sw: F64
    half: F64
    r: F64
    t: F64
    t2: F64
    den: F64
    zero: NDArray[np.bool_]
    at: NDArray[np.bool_]
    narrow: bool


def _soa_views(w: F64, mask: NDArray[np.bool_]) -> _SoaViews:
    m = w.shape[1]
    dm, nn, cc, c8 = w[22:30], w[30:32], w[32:34], w[34:42]
    narrow = m <= NARROW
    return _SoaViews(
        w[14:18],
        align_views(w[18:22]),
        dm,
        dm[:4],
        dm[4:],
        dm.reshape(2, 4, m),
        nn,
        nn[0],
        nn[1],
        cc,
        cc[0],
        cc[1],
        c8,
        c8[:4] if narrow else cc[0],
        c8[4:] if narrow else cc[1],
        w[18:22],
        c8[4:],
        w[42:45],
        w[45:48],
        w[48],  # dot
        w[49],  # sin_w
        w[50],  # sw
        w[51],  # half
        w[52],  # r
        w[53],  # t
        w[54],  # t2
        w[55],  # den
        mask[0],
        mask[1],
        narrow,
    )


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
    v = cached_views(scratch(S.shape[0]) if work is None else work, _soa_views)
    t0, q0, t1, b = end_views(A, B)
    q1, dot, r = v.q1, v.dot, v.r
    if shared is None:
        align_rows(q0, b, q1, dot, v.align)
        _sub(ONE, S, r)
    else:
        q1, dot, r = shared.q1, shared.dot, shared.r
    # Half chords d = q1 - q0 and m = q1 + q0 and their norms, in one block.
    _sub(q1, q0, v.d)
    _add(q1, q0, v.m)
    _mul(v.dm, v.dm, v.dm)
    _add_reduce(v.dm_sums, 1, None, v.nn)
    _sqrt(v.nn, v.nn)
    nd, nm, sin_w, half = v.nd, v.nm, v.sin_w, v.half
    _mul(nd, HALF, sin_w)
    _mul(sin_w, nm, sin_w)
    # s w = s 2 atan2(nd, nm); its half, s atan2(nd, nm), is the same bits over 2.
    _atan2(nd, nm, half)
    _mul(S, half, half)
    if not unit_s:
        _mul(half, TWO, v.sw)
    sin_sw, cos_sw, t, t2 = nd, nm, v.t, v.t2
    sincos_rows(v.sw, sin_sw, cos_sw, t, t2, check=not unit_s, half=half)
    # c0 = (sin w cos sw - cos w sin sw) / sin w, limit 1 - s; c1 = sin sw / sin w, limit s.
    zero = v.zero
    div, any0 = nonzero_divisor(sin_w, zero, v.den)
    _mul(sin_w, cos_sw, t)
    _mul(dot, sin_sw, t2)
    _sub(t, t2, t)
    ratio_or_limit(t, div, r, v.c0, zero, any0)
    ratio_or_limit(sin_sw, div, S, v.c1, zero, any0)
    p3 = v.p3
    _sub(t1, t0, p3)
    _mul(repeated(S, v.s3, v.narrow), p3, p3)
    _add(t0, p3, out[:3])
    if v.narrow:
        v.cc.take(X8, 0, v.c8, "clip")
    prod, prod1 = v.prod, v.prod1
    _mul(v.c8_0, q0, prod)
    _mul(v.c8_1, q1, prod1)
    _add(prod, prod1, out[3:])
    exact_ends(out, A, B, S, r, v.at, t, ends)


class _MotorViews(NamedTuple):
    """:func:`motor_lerp_rows`' views of a scratch."""

    q1: F64
    align: Align
    products: Products
    cross: Cross
    e9: F64  # rr, ss, rs repeated x 3 (narrow)
    rr3: F64  # e9's thirds, or (wide) rr, ss, rs
    ss3: F64
    rs3: F64
    dot3: F64
    cv: F64
    u3: F64
    v3: F64
    z3: F64
    x3: F64
    p: F64  # rr, ss, rs
    rr: F64
    ss: F64
    rs: F64
    r4: F64
    s4: F64
    qs: F64
    qs_rows: tuple[F64, F64, F64, F64]
    x4: F64
    bl: F64
    dot: F64
    r: F64
    x: F64
    y: F64
    at: NDArray[np.bool_]
    narrow: bool


def _motor_views(w: F64, mask: NDArray[np.bool_]) -> _MotorViews:
    e9, p, qs = w[34:43], w[61:64], w[30:34]
    narrow = w.shape[1] <= NARROW
    return _MotorViews(
        w[14:18],
        align_views(w[18:22]),
        products_views(w[14:22], w[22:34], w[34:46]),
        cross_views(w[22:34]),
        e9,
        e9[0:3] if narrow else p[0],
        e9[3:6] if narrow else p[1],
        e9[6:9] if narrow else p[2],
        w[43:46],
        w[46:49],
        w[49:52],
        w[52:55],
        w[55:58],
        w[58:61],
        p,
        p[0],
        p[1],
        p[2],
        w[22:26],
        w[26:30],
        qs,
        (qs[0], qs[1], qs[2], qs[3]),
        w[34:38],
        w[18:22],
        w[64],  # dot
        w[65],  # r
        w[66],  # x
        w[67],  # y
        mask[1],
        narrow,
    )


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
    v = cached_views(scratch(S.shape[0]) if work is None else work, _motor_views)
    t0, q0, t1, b = end_views(A, B)
    q1, dot, r = v.q1, v.dot, v.r
    if shared is None:
        align_rows(q0, b, q1, dot, v.align)
        _sub(ONE, S, r)
    else:
        q1, dot, r = shared.q1, shared.dot, shared.r
    u3, v3, z3 = v.u3, v.v3, v.z3
    if shared is not None and shared.cv is not None and shared.cross is not None:
        cross = shared.cross
    else:
        if shared is not None:
            _copyto(v.q1, q1)  # signed_products takes q from its block
        signed_products(q0, v.q1, C_VEC, v.cv, v.products)  # vector part of c = q0 q1*
        _sub(t0, t1, u3)
        cross_rows(u3, v.cv, v3, v.cross)
        cross = v3
    _mul(r, r, v.rr)
    _mul(S, S, v.ss)
    _mul(r, S, v.rs)
    narrow = v.narrow
    if narrow:
        v.p.take(X9, 0, v.e9, "clip")
    # num = rr t0 + ss t1 + rs (dot (t0 + t1) + (t0 - t1) x cv)
    _add(t0, t1, u3)
    _mul(repeated(dot, v.dot3, narrow), u3, u3)
    _add(u3, cross, u3)
    _mul(v.rs3, u3, u3)
    _mul(v.rr3, t0, v3)
    _mul(v.ss3, t1, z3)
    _add(v3, z3, v3)
    _add(v3, u3, v3)
    # den = rr + ss + 2 rs dot
    x, y = v.x, v.y
    _add(v.rr, v.ss, x)
    _mul(v.rs, TWO, y)
    _mul(y, dot, y)
    _add(x, y, x)
    _div(v3, repeated(x, v.x3, narrow), out[:3])
    # Rotation: the normalised quaternion blend r q0 + s q1.
    bl, qs = v.bl, v.qs
    _mul(repeated(r, v.r4, narrow), q0, bl)
    _mul(repeated(S, v.s4, narrow), q1, qs)
    _add(bl, qs, bl)
    _mul(bl, bl, qs)
    q_0, q_1, q_2, q_3 = v.qs_rows
    _add(q_0, q_1, x)
    _add(x, q_2, x)
    _add(x, q_3, x)
    _sqrt(x, x)
    _div(bl, repeated(x, v.x4, narrow), out[3:])
    exact_ends(out, A, B, S, r, v.at, x, ends)


class _DqViews(NamedTuple):
    """:func:`dq_slerp_rows`' views of a scratch."""

    q1: F64
    align: Align
    products: Products
    cross: Cross
    v: F64  # vector part of q1 q0*
    dut: F64  # d, u, t3 (the three terms of the position)
    dut_op: F64  # dut as the coefficients' operand: (9, M), or (wide) (3, 3, M)
    d: F64
    u: F64
    t3: F64
    sq: Dot3
    coef: F64  # kc, along, k kr
    kc: F64
    along: F64
    kk: F64
    coef9: F64  # coef repeated x 3 (9, M), or (wide) coef as (3, 1, M)
    kq: F64  # kr, k
    kr: F64
    k: F64
    k8: F64  # kq repeated x 4 (narrow)
    k8_0: F64  # the factors of q0 and q1: k8's halves, or (wide) kr and k
    k8_1: F64
    prod0: F64  # kr q0 and k q1
    prod1: F64
    div3: F64
    cos_phi: F64
    sin_phi: F64
    sphi: F64
    sin_s: F64
    cos_s: F64
    sin_r: F64
    r: F64
    x: F64
    y: F64
    den: F64
    zero: NDArray[np.bool_]
    at: NDArray[np.bool_]
    narrow: bool


def _dq_views(w: F64, mask: NDArray[np.bool_]) -> _DqViews:
    m = w.shape[1]
    dut, sq, coef, kq, k8 = w[22:31], w[31:34], w[46:49], w[49:51], w[51:59]
    narrow = m <= NARROW
    return _DqViews(
        w[14:18],
        align_views(w[18:22]),
        products_views(w[14:22], w[22:34], w[34:46]),
        cross_views(w[34:46]),
        w[59:62],
        dut,
        dut if narrow else dut.reshape(3, 3, m),
        dut[0:3],
        dut[3:6],
        dut[6:9],
        dot3_views(sq),
        coef,
        coef[0],
        coef[1],
        coef[2],
        w[34:43] if narrow else coef.reshape(3, 1, m),
        kq,
        kq[0],
        kq[1],
        k8,
        k8[:4] if narrow else kq[0],
        k8[4:] if narrow else kq[1],
        w[18:22],
        k8[4:],
        w[62:65],
        w[65],  # cos_phi
        w[66],  # sin_phi
        w[67],  # sphi
        w[68],  # sin_s
        w[69],  # cos_s
        w[70],  # sin_r
        w[71],  # r
        w[72],  # x
        w[73],  # y
        w[74],  # den
        mask[0],
        mask[1],
        narrow,
    )


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
    """Dual-quaternion ScLERP on the screw (:func:`interp.methods.dq_slerp`), in the
    world frame: with ``D = t1 - t0`` and ``q1 q0* = (cos phi, v)`` (``v = sin(phi) u``,
    the screw axis in world coordinates, to which ``R0`` maps ``methods``' body-frame
    ``t_d``, ``u``, ``v x t_d``), ``t = t0 + kc D + (s - kc) (D.u) u - k kr (v x D)``;
    the rotation ``q0 (cos s phi, k v_body)`` is ``kr q0 + k q1`` (SLERP): no vector
    is rotated."""
    v = cached_views(scratch(S.shape[0]) if work is None else work, _dq_views)
    t0, q0, t1, b = end_views(A, B)
    q1, cos_phi, r, vec = v.q1, v.cos_phi, v.r, v.v
    if shared is None:
        align_rows(q0, b, q1, cos_phi, v.align)
        _sub(ONE, S, r)
    else:
        q1, cos_phi, r = shared.q1, shared.dot, shared.r
    if shared is not None and shared.cv is not None:
        _negative(shared.cv, vec)  # vector part of q1 q0*: minus that of q0 q1*
    else:
        if shared is not None:
            _copyto(v.q1, q1)  # signed_products takes q from its block
        signed_products(q0, v.q1, REL_VEC_WORLD, vec, v.products)
    sin_phi, sphi, sin_s, cos_s = v.sin_phi, v.sphi, v.sin_s, v.cos_s
    dot3(vec, vec, v.sq, sin_phi)
    _sqrt(sin_phi, sin_phi)
    _atan2(sin_phi, cos_phi, sphi)  # phi in [0, pi/2]: cos_phi >= 0
    _mul(S, sphi, sphi)
    x, y = v.x, v.y
    sincos_rows(sphi, sin_s, cos_s, x, y, check=not unit_s)
    # (1-s) phi by angle addition: no further trig calls.
    cos_r, sin_r = sphi, v.sin_r
    _mul(sin_phi, cos_s, sin_r)
    _mul(cos_phi, sin_s, x)
    _sub(sin_r, x, sin_r)
    _mul(cos_phi, cos_s, cos_r)
    _mul(sin_phi, sin_s, x)
    _add(cos_r, x, cos_r)
    zero = v.zero
    div, any0 = nonzero_divisor(sin_phi, zero, v.den)
    k, kr, kc = v.k, v.kr, v.kc
    ratio_or_limit(sin_s, div, S, k, zero, any0)  # sin(s phi) / sin(phi), limit s
    ratio_or_limit(sin_r, div, r, kr, zero, any0)  # sin((1-s) phi) / sin(phi), limit 1 - s
    _mul(k, cos_r, kc)
    d, u, t3 = v.d, v.u, v.t3
    _sub(t1, t0, d)
    # Unit axis, or 0 without rotation (the along-axis term then has weight 0).
    _div(vec, repeated(div, v.div3, v.narrow), u)
    along = v.along
    dot3(d, u, v.sq, along)
    _sub(S, kc, x)
    _mul(x, along, along)
    # t = t0 + kc D + along u - (k kr) (v x D)
    if shared is not None and shared.cross is not None:
        _negative(shared.cross, t3)  # v x D = (-cv) x (t1 - t0) = -((t0 - t1) x cv)
    else:
        cross_rows(vec, d, t3, v.cross)
    _mul(k, kr, v.kk)
    if v.narrow:
        v.coef.take(X9, 0, v.coef9, "clip")
    _mul(v.coef9, v.dut_op, v.dut_op)
    _add(d, u, d)
    _sub(d, t3, d)
    _add(t0, d, out[:3])
    # q = kr q0 + k q1
    if v.narrow:
        v.kq.take(X8, 0, v.k8, "clip")
    _mul(v.k8_0, q0, v.prod0)
    _mul(v.k8_1, q1, v.prod1)
    _add(v.prod0, v.prod1, out[3:])
    exact_ends(out, A, B, S, r, v.at, x, ends)


#: The kernels that read :attr:`Shared.cv` and :attr:`Shared.cross`: worth computing
#: (``share_rows(..., products=True)``) when two of them run on the same rows.
SHARES_PRODUCTS: frozenset[RowKernel] = frozenset({motor_lerp_rows, dq_slerp_rows})

#: Each kernel's number in the compiled render kernels (``interp/_rowkernels.c``'s
#: ``pair_rows``; :mod:`interp.accel`): the same method, to float rounding.
COMPILED_KIND: dict[RowKernel, int] = {soa_rows: 0, motor_lerp_rows: 1, dq_slerp_rows: 2}
