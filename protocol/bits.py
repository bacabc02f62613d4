"""Vectorised bit packing for the compact pose codec: fixed-width and Exp-Golomb columns.

A bitstream is written MSB first. Values are written a *column* at a time (one
field of every entry), so that a reader can unpack a whole column with a few
numpy operations instead of a Python loop per value.

Exp-Golomb of order ``k`` (``v >= 0``): let ``q = v >> k`` and ``L`` its bit
length (0 for ``q == 0``); the code is ``L`` zeros and a one (the *prefix*),
then the ``L - 1`` bits of ``q`` below its leading one and the ``k`` low bits
of ``v`` (the *suffix*): ``L + 1 + max(L - 1, 0) + k`` bits. In a column every
prefix comes first, then every suffix, so a reader finds all the prefix lengths
with one ``flatnonzero`` and then gathers the suffixes at known offsets.

Signed values travel zigzagged (0, -1, 1, -2, ... -> 0, 1, 2, 3, ...).

Readers raise only ``RemoteProtocolError(BAD_FRAME)`` (truncated or overlong
codes) and never allocate more than a small multiple of the stream's size.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from posecast.protocol.errors import ErrorCode, RemoteProtocolError

__all__ = [
    "MAX_EG_BITS",
    "MAX_K",
    "SMALL",
    "BitReader",
    "BitWriter",
    "best_k",
    "bit_length",
    "eg_cost",
    "k_of_histogram",
    "unzigzag",
    "zigzag",
]

I64 = NDArray[np.int64]

#: Largest Exp-Golomb order a frame may state (a 4-bit field).
MAX_K = 15
#: Longest value an Exp-Golomb code may carry, in bits (prefix length + k).
MAX_EG_BITS = 48


def zigzag(v: I64) -> I64:
    """Signed to unsigned: 0, -1, 1, -2 -> 0, 1, 2, 3."""
    return (v << 1) ^ (v >> 63)


def unzigzag(z: I64) -> I64:
    """Inverse of :func:`zigzag`."""
    return (z >> 1) ^ -(z & 1)


def bit_length(v: I64) -> I64:
    """Bit length of each non-negative value (0 for 0); exact below 2**53."""
    return np.frexp(v.astype(np.float64))[1].astype(np.int64)


def eg_cost(v: I64, k: int) -> int:
    """Bits of the Exp-Golomb codes of order ``k`` of the non-negative values ``v``."""
    lengths = bit_length(v >> k)
    return int((2 * lengths + k + (lengths == 0)).sum())


_KS = np.arange(MAX_K + 1, dtype=np.int64)


#: Columns up to this many values go through the pure-Python paths (numpy's per-call
#: overhead dominates below it); longer ones through the vectorised paths.
SMALL = 256


def k_of_histogram(hist: list[int]) -> int:
    """The order coding values with these bit-length counts (``hist[b]``: how many
    have bit length b) in the fewest bits: see :func:`_best_k_small`."""
    n = sum(hist)
    below = 0  # #(b <= k)
    k = 0
    while k < MAX_K:
        below += hist[k]
        if below - (n - below - hist[k + 1]) >= 0:
            break
        k += 1
    return k


def _best_k_small(values: list[int]) -> tuple[int, int]:
    """:func:`best_k` of a short column, from a histogram of the bit lengths.

    With ``b`` a value's bit length, its code costs ``2 max(b - k, 0) + [b <= k] + k``
    bits, so ``cost(k + 1) - cost(k) = #(b <= k) - #(b > k + 1)``: non-decreasing in
    k (the cost is convex), and the first k where it is >= 0 is the first minimum
    (the one ``np.argmin`` picks).
    """
    n = len(values)
    hist = [0] * (MAX_EG_BITS + 2)
    for value in values:
        hist[value.bit_length()] += 1
    k = k_of_histogram(hist)
    cost = k * n
    for b, count in enumerate(hist):
        if count:
            cost += count * (2 * (b - k) if b > k else 1)
    return k, cost


def best_k(v: I64) -> tuple[int, int]:
    """The order in 0..MAX_K that codes ``v`` in the fewest bits, and that number of bits."""
    if v.size == 0:
        return 0, 0
    if v.size <= SMALL:
        return _best_k_small(v.tolist())
    lengths = bit_length(v[None, :] >> _KS[:, None])
    costs = (2 * lengths + (lengths == 0)).sum(axis=1) + _KS * v.size
    k = int(np.argmin(costs))
    return k, int(costs[k])


class BitWriter:
    """Collects fields (value, width) and packs them into bytes in one go.

    Fields are kept as Python ints: a frame has a few hundred, and a Python loop
    over a short column costs less than the numpy calls it would replace.
    """

    __slots__ = ("_owners", "_values", "_widths")

    def __init__(self) -> None:
        self._values: list[int] = []
        self._widths: list[int] = []
        self._owners: list[int] = []

    def fixed(self, values: I64, width: int, owners: I64) -> None:
        """Write each value in ``width`` bits (values must fit); ``owners``: entry of each."""
        if width and values.size:
            self._values += values.tolist()
            self._widths += [width] * values.size
            self._owners += owners.tolist()

    def bits_per_owner(self, n: int) -> I64:
        """Bits written for each of entries 0..n-1 (what each pose cost, framing excluded)."""
        if not self._widths:
            return np.zeros(n, np.int64)
        owners = np.array(self._owners, np.int64)
        widths = np.array(self._widths, np.float64)
        return np.bincount(owners, weights=widths, minlength=n).astype(np.int64)

    def exp_golomb(self, values: I64, k: int, owners: I64) -> None:
        """Write a column of non-negative values as Exp-Golomb codes of order ``k``."""
        if not values.size:
            return
        own = owners.tolist()
        prefix_widths = []
        suffixes = []
        suffix_widths = []
        for v in values.tolist():
            length = (v >> k).bit_length()
            # Prefix: L zeros then a one (the value 1 in L + 1 bits); suffix: v
            # without the leading one of v >> k (L - 1 + k bits), or v in k bits.
            prefix_widths.append(length + 1)
            if length:
                suffixes.append(v - (1 << (length - 1 + k)))
                suffix_widths.append(length - 1 + k)
            else:
                suffixes.append(v)
                suffix_widths.append(k)
        self._values += [1] * len(own)
        self._values += suffixes
        self._widths += prefix_widths
        self._widths += suffix_widths
        self._owners += own
        self._owners += own

    def getvalue(self) -> bytes:
        """The packed bits, zero-padded to whole bytes."""
        if len(self._values) > 8 * SMALL:
            return self._getvalue_numpy()
        acc = 0
        total = 0
        for value, width in zip(self._values, self._widths, strict=True):
            acc = (acc << width) | value
            total += width
        pad = -total % 8
        return (acc << pad).to_bytes((total + pad) // 8, "big")

    def _getvalue_numpy(self) -> bytes:
        # Long frames: shifting one growing int per field would be quadratic.
        values = np.array(self._values, np.int64)
        widths = np.array(self._widths, np.int64)
        keep = widths > 0
        values, widths = values[keep], widths[keep]
        total = int(widths.sum())
        ends = np.cumsum(widths)
        # For bit j of the stream: its field, and its shift inside that field.
        field = np.repeat(np.arange(values.size), widths)
        shift = ends[field] - 1 - np.arange(total)
        bits = ((values[field] >> shift) & 1).astype(np.uint8)
        return np.packbits(bits).tobytes()


#: Streams up to this many bits are read as one Python int (every read shifts it).
_SMALL_STREAM = 1 << 16


def _truncated() -> RemoteProtocolError:
    return RemoteProtocolError(ErrorCode.BAD_FRAME, "pose bitstream truncated")


class BitReader:
    """Reads columns back from packed bits; every failure is a BAD_FRAME error.

    Short columns (at most :data:`SMALL` values) are read from the stream as one
    Python int, long ones with numpy over the unpacked bits (made on first use).
    """

    __slots__ = ("_array", "_data", "_int", "_size", "pos")

    def __init__(self, data: bytes | memoryview) -> None:
        self._data = bytes(data)
        self._int = int.from_bytes(self._data, "big")
        self._size = 8 * len(self._data)
        self._array: NDArray[np.uint8] | None = None
        self.pos = 0

    @property
    def _bits(self) -> NDArray[np.uint8]:
        if self._array is None:
            self._array = np.unpackbits(np.frombuffer(self._data, np.uint8))
        return self._array

    @property
    def remaining(self) -> int:
        """Bits not read yet."""
        return self._size - self.pos

    def _take(self, width: int) -> int:
        """The next ``width`` bits as an int (the caller checked they are there)."""
        value = (self._int >> (self._size - self.pos - width)) & ((1 << width) - 1)
        self.pos += width
        return value

    def fixed(self, n: int, width: int) -> I64:
        """``n`` values of ``width`` bits each."""
        if width == 0 or n == 0:
            return np.zeros(n, np.int64)
        if n * width > self.remaining:
            raise _truncated()
        if n <= SMALL and self._size <= _SMALL_STREAM:
            packed = self._take(n * width)
            mask = (1 << width) - 1
            shifts = range(width * (n - 1), -1, -width)
            return np.array([(packed >> shift) & mask for shift in shifts], np.int64)
        chunk = self._bits[self.pos : self.pos + n * width].reshape(n, width).astype(np.int64)
        self.pos += n * width
        weights = np.int64(1) << np.arange(width - 1, -1, -1, dtype=np.int64)
        return chunk @ weights

    def exp_golomb(self, n: int, k: int) -> I64:
        """``n`` Exp-Golomb codes of order ``k`` (prefixes first, then suffixes)."""
        if n == 0:
            return np.zeros(0, np.int64)
        if n > self.remaining:
            raise _truncated()
        if n <= SMALL and self._size <= _SMALL_STREAM:
            return np.array(self._exp_golomb_small(n, k), np.int64)
        return self._exp_golomb_numpy(n, k)

    def _exp_golomb_small(self, n: int, k: int) -> list[int]:
        longest = MAX_EG_BITS - k
        x, size, pos = self._int, self._size, self.pos
        lengths = []
        for _ in range(n):
            # A prefix is at most MAX_EG_BITS - k zeros and a one: look no further.
            window = min(longest + 1, size - pos)
            if window <= 0:
                raise _truncated()
            chunk = (x >> (size - pos - window)) & ((1 << window) - 1)
            if not chunk:
                if window <= longest:
                    raise _truncated()
                raise RemoteProtocolError(ErrorCode.BAD_FRAME, "Exp-Golomb code too long")
            length = window - chunk.bit_length()
            lengths.append(length)
            pos += length + 1
        out = []
        for length in lengths:
            width = length - 1 + k if length else k
            if pos + width > size:
                raise _truncated()
            suffix = (x >> (size - pos - width)) & ((1 << width) - 1)
            pos += width
            out.append(suffix + (1 << (length - 1 + k)) if length else suffix)
        self.pos = pos
        return out

    def _exp_golomb_numpy(self, n: int, k: int) -> I64:
        # A prefix is at most MAX_EG_BITS - k zeros and a one: search no further.
        window = self._bits[self.pos : self.pos + n * (MAX_EG_BITS - k + 1)]
        ones = np.flatnonzero(window)[:n]
        if ones.size < n:
            raise _truncated()
        lengths = np.diff(ones, prepend=-1) - 1
        if int(lengths.max()) > MAX_EG_BITS - k:
            raise RemoteProtocolError(ErrorCode.BAD_FRAME, "Exp-Golomb code too long")
        self.pos += int(ones[-1]) + 1
        widths = np.maximum(lengths - 1, 0) + k
        total = int(widths.sum())
        if total > self.remaining:
            raise _truncated()
        suffix = np.zeros(n, np.int64)
        if total:
            # One row per suffix bit (never n x longest suffix: a hostile column of
            # one long code and many empty ones would allocate n * 48 words).
            nonzero = widths > 0
            w = widths[nonzero]
            ends = np.cumsum(w)
            owner = np.repeat(np.arange(w.size), w)
            shifts = ends[owner] - 1 - np.arange(total, dtype=np.int64)
            got = self._bits[self.pos : self.pos + total].astype(np.int64) << shifts
            suffix[nonzero] = np.add.reduceat(got, ends - w)
        self.pos += total
        lead = np.where(lengths > 0, np.int64(1) << np.maximum(lengths - 1 + k, 0), 0)
        return lead + suffix

    def finish(self) -> None:
        """Check that only zero padding (fewer than 8 bits) is left."""
        rest = self.remaining
        if rest >= 8 or self._int & ((1 << rest) - 1):
            raise RemoteProtocolError(ErrorCode.BAD_FRAME, "trailing bytes after the poses")
