"""Pure-Python paths of the compact pose codec for small frames (up to 30 entries).

The same layout as ``protocol.codec_frame`` (whose functions call these first),
written and read with Python ints, one list per column and one int for the whole
bitstream: a live update of 3 poses costs a few dozen numpy calls the other way,
each more than the arithmetic it does. Every output byte and decoded value is the
same (``tests/protocol/test_codec_small.py`` pins a hash of random frames).

The encoder takes validated inputs, like ``encode_frame``; anything unusual
(a duplicate stream, a time out of range, a baseline of another layout) returns
None and the caller takes the numpy path, which raises the error. The decoder
likewise returns None for any frame it would refuse, so the numpy path decides
every error: the two paths only share valid frames.
"""

from __future__ import annotations

import math
import struct
import zlib
from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from posecast.protocol.bits import MAX_EG_BITS
from posecast.protocol.codec_quant import M

__all__ = [
    "SMALL_FRAME",
    "Fallback",
    "Reader",
    "Writer",
    "baseline_list",
    "crc_rows",
    "predict_row",
    "unzz",
    "zz",
]

I64 = NDArray[np.int64]

#: Frames of at most this many entries take the pure-Python paths.
SMALL_FRAME = 30
_OTHERS = ((1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2))


class Fallback(Exception):
    """Not a case for the small path: the caller takes the numpy path."""


def zz(v: int) -> int:
    return v * 2 if v >= 0 else -2 * v - 1


def unzz(z: int) -> int:
    return (z >> 1) ^ -(z & 1)


class Writer:
    """One int for the bitstream and the bits each entry cost."""

    __slots__ = ("acc", "owned", "total")

    def __init__(self, n: int) -> None:
        self.acc = 0
        self.total = 0
        self.owned = [0] * n

    def fixed(self, values: list[int], width: int, owners: list[int]) -> None:
        col = 0
        for v in values:
            col = (col << width) | v
        self.acc = (self.acc << (width * len(values))) | col
        self.total += width * len(values)
        owned = self.owned
        for o in owners:
            owned[o] += width

    def eg(self, values: list[int], k: int, owners: list[int]) -> None:
        """A column of Exp-Golomb codes of order k: every prefix, then every suffix."""
        pre = npre = suf = nsuf = 0
        owned = self.owned
        for v, o in zip(values, owners, strict=True):
            if v >> k:
                # Prefix: L zeros and a one (L = bit length of v >> k); suffix: v
                # without its leading one (w = L - 1 + k bits).
                w = v.bit_length() - 1
                lead = w - k + 2
                pre = (pre << lead) | 1
                suf = (suf << w) | (v ^ (1 << w))
                npre += lead
                nsuf += w
                owned[o] += lead + w
            else:
                pre = (pre << 1) | 1
                suf = (suf << k) | v
                npre += 1
                nsuf += k
                owned[o] += 1 + k
        self.acc = (((self.acc << npre) | pre) << nsuf) | suf
        self.total += npre + nsuf

    def getvalue(self) -> bytes:
        pad = -self.total % 8
        return (self.acc << pad).to_bytes((self.total + pad) // 8, "big")


def _sources(i0: int, idx: int) -> tuple[int, int, int, int]:
    """Where, in (a, b, c, dropped) of a row of largest index i0, the full quaternion's
    components ``_OTHERS[idx]`` and its component ``idx`` (the sign) are."""
    at = {o: j for j, o in enumerate(_OTHERS[i0])}
    at[i0] = 3
    o0, o1, o2 = _OTHERS[idx]
    return at[o0], at[o1], at[o2], at[idx]


_SOURCES = [[_sources(i0, idx) for idx in range(4)] for i0 in range(4)]


def predict_row(base: list[int], idx: int) -> list[int]:
    """``codec_quant.predict_rotation`` of one baseline row (the same integer steps)."""
    i0, a, b, c = base[0], base[1], base[2], base[3]
    if i0 == idx and -M <= a <= M and -M <= b <= M and -M <= c <= M:
        # The dropped component (>= 0) stays dropped: sign +1, nothing to clip.
        return [a, b, c]
    rest = max(0, 2 * M * M - (a * a + b * b + c * c))
    full = (a, b, c, (math.floor(math.sqrt(4.0 * rest)) + 1) // 2)
    j0, j1, j2, js = _SOURCES[i0][idx]
    if full[js] < 0:
        return [min(M, max(-M, -full[j0])), min(M, max(-M, -full[j1])), min(M, max(-M, -full[j2]))]
    return [min(M, max(-M, full[j0])), min(M, max(-M, full[j1])), min(M, max(-M, full[j2]))]


def crc_rows(rows: list[list[int]], size: int) -> int:
    """``codec_frame._check``: CRC-32 of the rows as int32 LE, cut to ``size`` bytes."""
    flat = [v & 0xFFFFFFFF for row in rows for v in row]
    return zlib.crc32(struct.pack(f"<{len(flat)}I", *flat)) & ((1 << (8 * size)) - 1)


def baseline_list(key: Any, baselines: Mapping[Any, I64], width: int) -> list[int]:
    """A baseline row as ints; Fallback if missing or not an int64 row of ``width``."""
    row = baselines.get(key)
    if type(row) is not np.ndarray or row.dtype != np.int64 or row.shape != (width,):
        raise Fallback
    out: list[int] = row.tolist()
    return out


class Reader:
    """Columns from one Python int; Fallback on anything the numpy path would refuse."""

    __slots__ = ("pos", "size", "x")

    def __init__(self, data: bytes) -> None:
        self.x = int.from_bytes(data, "big")
        self.size = 8 * len(data)
        self.pos = 0

    def fixed(self, n: int, width: int) -> list[int]:
        if not n:
            return []
        if self.pos + n * width > self.size:
            raise Fallback
        packed = (self.x >> (self.size - self.pos - n * width)) & ((1 << (n * width)) - 1)
        self.pos += n * width
        mask = (1 << width) - 1
        return [(packed >> s) & mask for s in range(width * (n - 1), -1, -width)]

    def eg(self, n: int, k: int) -> list[int]:
        x, size, pos = self.x, self.size, self.pos
        longest = MAX_EG_BITS - k
        lengths = []
        for _ in range(n):
            window = min(longest + 1, size - pos)
            if window <= 0:
                raise Fallback
            chunk = (x >> (size - pos - window)) & ((1 << window) - 1)
            if not chunk:
                raise Fallback
            length = window - chunk.bit_length()
            lengths.append(length)
            pos += length + 1
        out = []
        for length in lengths:
            width = length - 1 + k if length else k
            if pos + width > size:
                raise Fallback
            suffix = (x >> (size - pos - width)) & ((1 << width) - 1)
            pos += width
            out.append(suffix + (1 << width) if length else suffix)
        self.pos = pos
        return out

    def finish(self) -> None:
        rest = self.size - self.pos
        if rest >= 8 or self.x & ((1 << rest) - 1):
            raise Fallback
