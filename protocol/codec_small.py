"""Pure-Python helpers of the compact pose codec for small frames (up to 30 entries).

The small paths (``protocol.codec_fast``, ``protocol.codec_relay``) write and read
the layout of ``protocol.codec_frame`` with Python ints: one list per column, one
int for the whole bitstream (``protocol.bits.IntWriter`` and ``IntReader``). A
live update of 3 poses costs a few dozen numpy calls the other way, each more
than the arithmetic it does. Every output byte and decoded value is the same
(``tests/protocol/test_codec_small.py`` pins a hash of random frames).

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

from posecast.protocol.codec_quant import M

__all__ = [
    "SMALL_FRAME",
    "Fallback",
    "baseline_list",
    "crc_rows",
    "predict_row",
]

I64 = NDArray[np.int64]

#: Frames of at most this many entries take the pure-Python paths.
SMALL_FRAME = 30
_OTHERS = ((1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2))


class Fallback(Exception):
    """Not a case for the small path: the caller takes the numpy path."""


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
