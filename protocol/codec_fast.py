"""Small frames (up to ``SMALL_FRAME`` entries) encoded and decoded in pure Python.

``protocol.codec`` tries these first; they return None for anything else (a big
frame, an input or frame the numpy path of ``protocol.codec_frame`` would refuse),
and the numpy path then does the work or raises the error. Same bytes, same values.
"""

from __future__ import annotations

import math
import struct
import zlib
from collections.abc import Mapping
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from posecast.protocol import _accel
from posecast.protocol.bits import IntReader, IntWriter, best_k_small, unzz, zz
from posecast.protocol.codec_frame import (
    CODEC_MAGIC,
    CODEC_VERSION,
    F_UPDATE,
    F_VELOCITY,
    Encoded,
    PoseFrame,
    _min_entry_bits,
    _read_header,
    _read_uvarint,
    _svarint,
    _uvarint,
)
from posecast.protocol.codec_quant import (
    _ANG_CODE_MAX,
    _LIN_CODE_MAX,
    ROTATION_BITS,
    M,
    Volume,
    codes_problem_rows,
)
from posecast.protocol.codec_small import (
    SMALL_FRAME,
    Fallback,
    baseline_list,
    crc_rows,
    predict_row,
)
from posecast.protocol.errors import RemoteProtocolError

__all__ = [
    "UpdateGeometry",
    "decode_small",
    "decode_update_rows",
    "encode_small",
    "read_varint",
]

I64 = NDArray[np.int64]
_F_SPLIT = 4
_TIME_MS_LIMIT = 1 << 30
_US_LIMIT = 1 << 62
_ID_MAX = 0xFFFF
Rows = list[list[int]]


def _ids_times(
    w: IntWriter, users: list[int], streams: list[int], off: list[int], sel: list[int], update: bool
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
        w.eg_column(ug, 0, sel)
    w.eg_column(sg, 0, sel)
    k = best_k_small(first)[0]
    w.eg_column(first, k, first_own)
    w.eg_column(same, 0, same_own)
    return k


def _classed(w: IntWriter, z: Rows, cls: list[int], sel: list[int]) -> list[int]:
    """Zigzagged differences (3 a row), class 0 entries then class 1 per column."""
    parts = []
    for want in (0, 1):
        own = [i for i, c in zip(sel, cls, strict=True) if c == want]
        rows = [row for row, c in zip(z, cls, strict=True) if c == want]
        parts.append((own, rows, best_k_small([v for row in rows for v in row])[0]))
    for j in range(3):
        for own, rows, k in parts:
            if own:
                w.eg_column([row[j] for row in rows], k, own)
    return [parts[0][2], parts[1][2]]


def _key_section(
    w: IntWriter,
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
            k = best_k_small([v for r in z for v in r])[0]
            nib.append(k)
            for j in range(3):
                w.eg_column([r[j] for r in z], k, sel)
    return nib


def _delta_section(
    w: IntWriter,
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
    w.eg_column([(r[0] - b[0]) & 3 for r, b in zip(rows, base, strict=True)], 0, sel)
    z = []
    for r, b in zip(rows, base, strict=True):
        p = predict_row(b, r[0])
        d0, d1, d2 = r[1] - p[0], r[2] - p[1], r[3] - p[2]
        z.append([zz(d0), zz(d1), zz(d2)])
    nib += _classed(w, z, cls, sel)
    for lo in range(4, len(rows[0]), 3):
        z = []
        for r, b in zip(rows, base, strict=True):
            d0, d1, d2 = r[lo] - b[lo], r[lo + 1] - b[lo + 1], r[lo + 2] - b[lo + 2]
            z.append([zz(d0), zz(d1), zz(d2)])
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
        w = IntWriter(n)
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
    r: IntReader, n: int, k: int, update: bool
) -> tuple[list[int], list[int], list[int]]:
    ug = [0] * n if update else r.eg_column(n, 0)
    sg = r.eg_column(n, 0)
    new = [g > 0 for g in ug]
    new[0] = True
    n_first = sum(new)
    first = [unzz(z) for z in r.eg_column(n_first, k)]
    same = [unzz(z) for z in r.eg_column(n - n_first, 0)]
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


def _read_classed(r: IntReader, cls: list[int], ks: list[int], out: Rows, lo: int) -> None:
    for j in range(3):
        for want in (0, 1):
            idx = [i for i, c in enumerate(cls) if c == want]
            for i, z in zip(idx, r.eg_column(len(idx), ks[want]), strict=True):
                out[i][lo + j] += unzz(z)


def _read_sections(
    r: IntReader, h: Any, volume: Volume, baselines: Mapping[Any, I64]
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
            cols += [[unzz(z) for z in r.eg_column(n, k)] for _ in range(3)]
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
        steps = r.eg_column(n, 0)
        out = [[(b[0] + d) & 3] + [0] * (h.width - 1) for b, d in zip(base, steps, strict=True)]
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
        r = IntReader(data[h.size :])
        users, streams, off, rows = _read_sections(r, h, volume, baselines or {})
        r.finish()
    except (Fallback, RemoteProtocolError):
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


# --------------------------------------------------------------------------- updates
#
# The relay decodes one small update per client and tick: the path below reads
# one straight from its bytes into code rows (Python ints), with the baselines as
# rows of ints, and builds no frame, no numpy array and no list per column. It
# returns None for anything it would not accept, exactly like ``decode_small``:
# the caller then takes the reference path, which accepts the frame or raises
# its error. Checks that cannot fail for a baseline are left out: the decoder
# stores only rows this path or the reference path validated.
#
# The bitstream is read with ``bits.IntReader`` (a prefix's end is a ``str.find``,
# a suffix a shift and a mask).

_CHECK_ROW = {7: struct.Struct("<7i"), 13: struct.Struct("<13i")}
UpdateRows = tuple[list[int], list[int], Rows]


class UpdateGeometry:
    """What the update path needs of a volume, computed once per decoder."""

    __slots__ = ("delta_bits", "key_bits", "packed", "top", "volume", "widths")

    def __init__(self, volume: Volume) -> None:
        self.volume = volume
        self.widths = volume.bits
        self.top = tuple((1 << b) - 1 for b in volume.bits)
        self.key_bits = {v: _min_entry_bits(True, v, volume)[0] for v in (False, True)}
        self.delta_bits = {v: _min_entry_bits(True, v, volume)[1] for v in (False, True)}
        #: All of it as one tuple of ints, for the compiled path.
        self.packed = (
            *self.widths,
            *self.top,
            *(self.key_bits[v] for v in (False, True)),
            *(self.delta_bits[v] for v in (False, True)),
        )


def _update_ids(r: IntReader, n: int, k: int) -> tuple[list[int], list[int]]:
    """Streams and ms offsets of an update section (no user column: every user is 0)."""
    sg = r.eg_column(n, 0)
    z = r.eg_column(1, k)[0]
    same = r.eg_column(n - 1, 0)
    s = sg[0]
    o = unzz(z)
    if s > _ID_MAX or abs(o) >= _TIME_MS_LIMIT:
        raise Fallback
    streams, off = [s], [o]
    for d, z in zip(sg[1:], same, strict=True):
        step = unzz(z)
        if d > _ID_MAX or abs(step) >= _TIME_MS_LIMIT:
            raise Fallback
        s += d + 1
        o += step
        if s > _ID_MAX or abs(o) >= _TIME_MS_LIMIT:
            raise Fallback
        streams.append(s)
        off.append(o)
    return streams, off


def _update_keys(r: IntReader, n: int, width: int, nib: list[int], g: UpdateGeometry) -> Rows:
    """The code rows of an update's key section (after its ids and times)."""
    cols = [r.fixed(n, 2)]
    for _ in range(3):
        cols.append([v - M for v in r.fixed(n, ROTATION_BITS)])
    for b in g.widths:
        cols.append(r.fixed(n, b))
    rows = [list(row) for row in zip(*cols, strict=True)]
    if width == 13:
        for row in rows:
            row += (0, 0, 0, 0, 0, 0)
        r.add_columns([(rows, c, nib[1 if c < 10 else 2]) for c in range(7, 13)])
    return rows


def _update_deltas(
    r: IntReader, streams: list[int], width: int, nib: list[int], base: Rows, split: bool
) -> Rows:
    """The code rows of an update's delta section (after its ids and times)."""
    out = []
    for b, d in zip(base, r.eg_column(len(streams), 0), strict=True):
        idx = (b[0] + d) & 3
        # A baseline is a valid row: the same idx predicts its own components.
        row = b[:] if idx == b[0] else [idx, *predict_row(b, idx), *b[4:]]
        out.append(row)
    # Class 1: every stream but stream 0, when the frame splits classes.
    if not split:
        classes = [out, []]
    elif 0 in streams:
        classes = [[out[streams.index(0)]], [row for row, s in zip(out, streams, strict=True) if s]]
    else:
        classes = [[], out]
    jobs = []
    for at, lo in enumerate(range(1, width, 3)):
        for c in range(lo, lo + 3):
            for want in (0, 1):
                if classes[want]:
                    jobs.append((classes[want], c, nib[1 + 2 * at + want]))
    r.add_columns(jobs)
    return out


def _rows_valid(rows: Rows, top: tuple[int, ...]) -> bool:
    """``codes_problem_rows(rows) is None`` (every idx is 0..3 here by construction)."""
    lim = 2 * M * M
    tx, ty, tz = top
    for r in rows:
        a, b, c = r[1], r[2], r[3]
        if not (-M <= a <= M and -M <= b <= M and -M <= c <= M and a * a + b * b + c * c <= lim):
            return False
        if not (0 <= r[4] <= tx and 0 <= r[5] <= ty and 0 <= r[6] <= tz):
            return False
        if len(r) == 13 and not (
            max(abs(r[7]), abs(r[8]), abs(r[9])) <= _LIN_CODE_MAX
            and max(abs(r[10]), abs(r[11]), abs(r[12])) <= _ANG_CODE_MAX
        ):
            return False
    return True


def read_varint(data: bytes, pos: int) -> tuple[int, int]:
    """``codec_frame._read_uvarint``, one-byte values without a loop (the usual case);
    raises ``RemoteProtocolError`` (or IndexError) likewise."""
    byte = data[pos]
    if byte < 0x80:
        return byte, pos + 1
    return _read_uvarint(data, pos)


def _update_header(data: bytes, pos: int, velocity: bool) -> tuple[int, int, int, list[int], int]:
    """(n_key, n_delta, check, nibbles, offset of the bitstream) after the base time."""
    nk, pos = read_varint(data, pos)
    nd, pos = read_varint(data, pos)
    size = len(data)
    check = -1
    if nd:
        if pos + 2 > size:
            raise Fallback
        check = data[pos] | data[pos + 1] << 8
        pos += 2
    n_nib = (1 + (2 if velocity else 0) if nk else 0) + (5 + (4 if velocity else 0) if nd else 0)
    end = pos + (n_nib + 1) // 2
    if end > size:
        raise Fallback
    nib: list[int] = []
    for byte in data[pos:end]:
        nib += (byte >> 4, byte & 0x0F)
    if len(nib) > n_nib and nib.pop():
        raise Fallback
    return nk, nd, check, nib, end


def decode_update_rows(
    data: bytes,
    pos: int,
    flags: int,
    geometry: UpdateGeometry,
    baselines: Mapping[int, list[int]],
) -> UpdateRows | None:
    """Streams (ascending), ms offsets and code rows of a small valid update frame
    whose header up to the base time is read (``pos``: what follows it; ``flags``
    checked by the caller); None for anything else (take the reference path).

    ``baselines``: stream -> code row (Python ints) that the caller validated.
    The compiled accelerator (``protocol._accel``) does the same when it runs.
    """
    fast = _accel.speedups
    if fast is not None and type(baselines) is dict:
        got: UpdateRows | None = fast.decode_update_rows(
            data, pos, flags, geometry.packed, baselines
        )
        return got
    velocity = bool(flags & F_VELOCITY)
    width = 13 if velocity else 7
    try:
        nk, nd, check, nib, pos = _update_header(data, pos, velocity)
        n = nk + nd
        need = nk * geometry.key_bits[velocity] + nd * geometry.delta_bits[velocity]
        if not 0 < n <= SMALL_FRAME or need > 8 * (len(data) - pos):
            return None
        r = IntReader(data[pos:])
        streams: list[int] = []
        off: list[int] = []
        rows: Rows = []
        if nk:
            streams, off = _update_ids(r, nk, nib[0])
            rows = _update_keys(r, nk, width, nib, geometry)
            nib = nib[1 + (2 if velocity else 0) :]
        if nd:
            s, o = _update_ids(r, nd, nib[0])
            base = [baselines[x] for x in s]
            if any(len(b) != width for b in base):
                return None
            pack = _CHECK_ROW[width].pack
            if zlib.crc32(b"".join([pack(*b) for b in base])) & 0xFFFF != check:
                return None
            out = _update_deltas(r, s, width, nib, base, bool(flags & _F_SPLIT))
            streams, off, rows = streams + s, off + o, rows + out
        if not r.rest_is_padding():
            return None
    except (Fallback, KeyError, IndexError, ValueError, RemoteProtocolError, struct.error):
        return None
    if not _rows_valid(rows, geometry.top):
        return None
    if nk and nd:
        order = sorted(range(n), key=streams.__getitem__)
        streams = [streams[i] for i in order]
        off = [off[i] for i in order]
        rows = [rows[i] for i in order]
    if len(set(streams)) != n:
        return None
    return streams, off, rows
