"""Small frames (up to ``SMALL_FRAME`` entries) encoded and decoded in pure Python.

``protocol.codec`` tries these first; they return None for anything else (a big
frame, an input or frame the numpy path of ``protocol.codec_frame`` would refuse),
and the numpy path then does the work or raises the error. Same bytes, same values.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from protocol.bits import _best_k_small
from protocol.codec_frame import (
    CODEC_MAGIC,
    CODEC_VERSION,
    F_UPDATE,
    Encoded,
    PoseFrame,
    _read_header,
    _svarint,
    _uvarint,
)
from protocol.codec_quant import ROTATION_BITS, M, Volume, codes_problem_rows
from protocol.codec_small import (
    SMALL_FRAME,
    Fallback,
    Reader,
    Writer,
    baseline_list,
    crc_rows,
    predict_row,
    unzz,
    zz,
)

__all__ = ["decode_small", "encode_small"]

I64 = NDArray[np.int64]
_F_SPLIT = 4
_TIME_MS_LIMIT = 1 << 30
_US_LIMIT = 1 << 62
_ID_MAX = 0xFFFF
Rows = list[list[int]]


def _ids_times(
    w: Writer, users: list[int], streams: list[int], off: list[int], sel: list[int], update: bool
) -> int:
    """The ug, sg, t_first and t_same columns of a section; the t_first order."""
    ug, sg, first, first_own, same, same_own = [], [], [], [], [], []
    pu, ps, po = 0, -1, 0
    for i in sel:
        u, s, o = users[i], streams[i], off[i]
        g = u - pu
        ug.append(g)
        if g > 0 or i == sel[0]:
            sg.append(s)
            first.append(zz(o))
            first_own.append(i)
        else:
            sg.append(s - ps - 1)
            same.append(zz(o - po))
            same_own.append(i)
        pu, ps, po = u, s, o
    if not update:
        w.eg(ug, 0, sel)
    w.eg(sg, 0, sel)
    k = _best_k_small(first)[0]
    w.eg(first, k, first_own)
    w.eg(same, 0, same_own)
    return k


def _classed(w: Writer, z: Rows, cls: list[int], sel: list[int]) -> list[int]:
    """Zigzagged differences (3 a row), class 0 entries then class 1 per column."""
    parts = []
    for want in (0, 1):
        own = [i for i, c in zip(sel, cls, strict=True) if c == want]
        rows = [row for row, c in zip(z, cls, strict=True) if c == want]
        parts.append((own, rows, _best_k_small([v for row in rows for v in row])[0]))
    for j in range(3):
        for own, rows, k in parts:
            if own:
                w.eg([row[j] for row in rows], k, own)
    return [parts[0][2], parts[1][2]]


def _key_section(
    w: Writer,
    cols: tuple[list[int], list[int], list[int], Rows],
    sel: list[int],
    update: bool,
    volume: Volume,
) -> list[int]:
    users, streams, off, codes = cols
    nib = [_ids_times(w, users, streams, off, sel, update)]
    rows = [codes[i] for i in sel]
    w.fixed([r[0] for r in rows], 2, sel)
    for j in (1, 2, 3):
        w.fixed([r[j] + M for r in rows], ROTATION_BITS, sel)
    for j, bits in zip((4, 5, 6), volume.bits, strict=True):
        w.fixed([r[j] for r in rows], bits, sel)
    if rows and len(rows[0]) == 13:
        for lo in (7, 10):
            z = [[zz(v) for v in r[lo : lo + 3]] for r in rows]
            k = _best_k_small([v for r in z for v in r])[0]
            nib.append(k)
            for j in range(3):
                w.eg([r[j] for r in z], k, sel)
    return nib


def _delta_section(
    w: Writer,
    cols: tuple[list[int], list[int], list[int], Rows],
    sel: list[int],
    base: Rows,
    update: bool,
    split: bool,
) -> list[int]:
    users, streams, off, codes = cols
    nib = [_ids_times(w, users, streams, off, sel, update)]
    rows = [codes[i] for i in sel]
    cls = [int(split and streams[i] != 0) for i in sel]
    w.eg([(r[0] - b[0]) & 3 for r, b in zip(rows, base, strict=True)], 0, sel)
    z = []
    for r, b in zip(rows, base, strict=True):
        p = predict_row(b, r[0])
        d0, d1, d2 = r[1] - p[0], r[2] - p[1], r[3] - p[2]
        z.append([(d0 << 1) ^ (d0 >> 63), (d1 << 1) ^ (d1 >> 63), (d2 << 1) ^ (d2 >> 63)])
    nib += _classed(w, z, cls, sel)
    for lo in range(4, len(rows[0]), 3):
        z = []
        for r, b in zip(rows, base, strict=True):
            d0, d1, d2 = r[lo] - b[lo], r[lo + 1] - b[lo + 1], r[lo + 2] - b[lo + 2]
            z.append([(d0 << 1) ^ (d0 >> 63), (d1 << 1) ^ (d1 >> 63), (d2 << 1) ^ (d2 >> 63)])
        nib += _classed(w, z, cls, sel)
    return nib


def _sorted(
    users: I64, streams: I64, capture_times: NDArray[np.float64], codes: I64, base: float
) -> tuple[list[int], list[int], list[int], Rows]:
    """The entries sorted by (user, stream), times as ms offsets; Fallback if refused."""
    off = []
    for t in capture_times.tolist():
        if not math.isfinite(t):
            raise Fallback
        o = round((base - t) * 1000.0)
        if abs(o) >= _TIME_MS_LIMIT:
            raise Fallback
        off.append(o)
    us, ss, rows = users.tolist(), streams.tolist(), codes.tolist()
    order = sorted(range(len(us)), key=lambda i: (us[i] << 16) | ss[i])
    keys = [(us[i] << 16) | ss[i] for i in order]
    if len(set(keys)) != len(keys):
        raise Fallback
    return (
        [us[i] for i in order],
        [ss[i] for i in order],
        [off[i] for i in order],
        [rows[i] for i in order],
    )


def encode_small(
    flags: int,
    number: int,
    base_time: float,
    users: I64,
    streams: I64,
    capture_times: NDArray[np.float64],
    codes: I64,
    volume: Volume,
    baselines: Mapping[Any, I64] | None,
    split: bool,
) -> Encoded | None:
    """``codec_frame.encode_frame`` of a small frame, or None (take the numpy path)."""
    n = codes.shape[0]
    if not 0 < n <= SMALL_FRAME or type(number) is not int or not 0 <= number < (1 << 63):
        return None
    if not math.isfinite(base_time) or abs(base_time) * 1e6 >= _US_LIMIT:
        return None
    base_us = round(base_time * 1e6)
    base = base_us / 1e6
    update = bool(flags & F_UPDATE)
    if split:
        flags |= _F_SPLIT
    try:
        cols = _sorted(users, streams, capture_times, codes, base)
        us, ss, off, rows = cols
        names: list[Any] = ss if update else list(zip(us, ss, strict=True))
        is_delta = [name in baselines for name in names] if baselines else [False] * n
        kd = [i for i in range(n) if not is_delta[i]]
        dd = [i for i in range(n) if is_delta[i]]
        w = Writer(n)
        nib: list[int] = []
        check = b""
        if kd:
            nib += _key_section(w, cols, kd, update, volume)
        if dd:
            assert baselines
            base_rows = [baseline_list(names[i], baselines, len(rows[0])) for i in dd]
            if codes_problem_rows(base_rows, volume) is not None:
                return None
            size = 2 if update else 4
            check = crc_rows(base_rows, size).to_bytes(size, "little")
            nib += _delta_section(w, cols, dd, base_rows, update, split)
    except Fallback:
        return None
    if len(nib) % 2:
        nib.append(0)
    header = (
        bytes([CODEC_MAGIC, flags | (CODEC_VERSION << 4)])
        + _uvarint(number)
        + _svarint(base_us)
        + _uvarint(len(kd))
        + _uvarint(len(dd))
        + check
        + bytes((a << 4) | b for a, b in zip(nib[::2], nib[1::2], strict=True))
    )
    kind: Literal["snapshot", "update"] = "update" if update else "snapshot"
    frame = PoseFrame(
        kind,
        number,
        base,
        np.array(us, np.int64),
        np.array(ss, np.int64),
        np.array([base - o / 1000.0 for o in off], np.float64),
        np.array(rows, np.int64).reshape(n, codes.shape[1]),
        np.array(is_delta, bool),
        volume,
    )
    return Encoded(header + w.getvalue(), frame, np.array(w.owned, np.int64))


def _read_ids_times(
    r: Reader, n: int, k: int, update: bool
) -> tuple[list[int], list[int], list[int]]:
    ug = [0] * n if update else r.eg(n, 0)
    sg = r.eg(n, 0)
    new = [g > 0 for g in ug]
    new[0] = True
    n_first = sum(new)
    first = [unzz(z) for z in r.eg(n_first, k)]
    same = [unzz(z) for z in r.eg(n - n_first, 0)]
    users, streams, off = [], [], []
    u, s, o = 0, -1, 0
    fi = si = 0
    for g, d, is_new in zip(ug, sg, new, strict=True):
        if g > _ID_MAX or d > _ID_MAX:
            raise Fallback
        u += g
        if is_new:
            s = d
            o = first[fi]
            fi += 1
        else:
            s += d + 1
            step = same[si]
            si += 1
            if abs(step) >= _TIME_MS_LIMIT:
                raise Fallback
            o += step
        if u > _ID_MAX or s > _ID_MAX or abs(o) >= _TIME_MS_LIMIT:
            raise Fallback
        users.append(u)
        streams.append(s)
        off.append(o)
    return users, streams, off


def _read_classed(r: Reader, cls: list[int], ks: list[int], out: Rows, lo: int) -> None:
    for j in range(3):
        for want in (0, 1):
            idx = [i for i, c in enumerate(cls) if c == want]
            for i, z in zip(idx, r.eg(len(idx), ks[want]), strict=True):
                out[i][lo + j] += unzz(z)


def _read_sections(
    r: Reader, h: Any, volume: Volume, baselines: Mapping[Any, I64]
) -> tuple[list[int], list[int], list[int], Rows]:
    nib = iter(h.nibbles)
    users: list[int] = []
    streams: list[int] = []
    off: list[int] = []
    rows: Rows = []
    if h.n_key:
        n = h.n_key
        u, s, o = _read_ids_times(r, n, next(nib), h.update)
        cols = [r.fixed(n, 2)] + [[v - M for v in r.fixed(n, ROTATION_BITS)] for _ in range(3)]
        cols += [r.fixed(n, bits) for bits in volume.bits]
        for _ in range(7, h.width, 3):
            k = next(nib)
            cols += [[unzz(z) for z in r.eg(n, k)] for _ in range(3)]
        users, streams, off = u, s, o
        rows = [list(t) for t in zip(*cols, strict=True)]
    if h.n_delta:
        n = h.n_delta
        u, s, o = _read_ids_times(r, n, next(nib), h.update)
        names: list[Any] = s if h.update else list(zip(u, s, strict=True))
        base = [baseline_list(name, baselines, h.width) for name in names]
        if codes_problem_rows(base, volume) is not None:
            raise Fallback
        if crc_rows(base, 2 if h.update else 4) != h.check:
            raise Fallback
        cls = [int(h.split and x != 0) for x in s]
        out = [
            [(b[0] + d) & 3] + [0] * (h.width - 1) for b, d in zip(base, r.eg(n, 0), strict=True)
        ]
        for row, b in zip(out, base, strict=True):
            row[1:4] = predict_row(b, row[0])
            row[4:] = b[4:]
        for lo in range(1, h.width, 3):
            _read_classed(r, cls, [next(nib), next(nib)], out, lo)
        users, streams, off, rows = users + u, streams + s, off + o, rows + out
    return users, streams, off, rows


def decode_small(
    data: bytes, volume: Volume, baselines: Mapping[Any, I64] | None, want_update: bool
) -> PoseFrame | None:
    """``codec_frame.decode_frame`` of a small valid frame, else None (numpy path)."""
    data = bytes(data)
    try:
        h = _read_header(data, want_update, volume)
    except Exception:
        return None
    n = h.n_key + h.n_delta
    if not 0 < n <= SMALL_FRAME:
        return None
    try:
        r = Reader(data[h.size :])
        users, streams, off, rows = _read_sections(r, h, volume, baselines or {})
        r.finish()
    except Fallback:
        return None
    if codes_problem_rows(rows, volume) is not None:
        return None
    order = sorted(range(n), key=lambda i: (users[i] << 16) | streams[i])
    keys = [(users[i] << 16) | streams[i] for i in order]
    if len(set(keys)) != n:
        return None
    base = h.base_us / 1e6
    kind: Literal["snapshot", "update"] = "update" if h.update else "snapshot"
    return PoseFrame(
        kind,
        h.number,
        base,
        np.array([users[i] for i in order], np.int64),
        np.array([streams[i] for i in order], np.int64),
        np.array([base - off[i] / 1000.0 for i in order], np.float64),
        np.array([rows[i] for i in order], np.int64).reshape(n, h.width),
        np.array([i >= h.n_key for i in order], bool),
        volume,
    )
