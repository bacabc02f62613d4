"""Bit packing, Exp-Golomb and zigzag: the one module every compact layout codes bits with.

Sections, in order:

- **zigzag**: signed to unsigned (0, -1, 1, -2, ... -> 0, 1, 2, 3, ...): :func:`zz`
  and :func:`unzz`, one expression each for Python ints and int64 arrays alike.
- **Exp-Golomb**: the code, its tables, and the choice of its order ``k``.
- **Python-int streams**: :class:`IntWriter` and :class:`IntReader`, a bitstream as
  one Python int, for frames of a few dozen entries (every relay update and
  snapshot): ``codec_fast``, ``codec_small`` and ``codec_relay`` write and read with them.
- **numpy streams**: :class:`BitWriter` and :class:`BitReader`, columns of any
  length (``codec_frame``'s reference path).

A bitstream is written MSB first. Exp-Golomb of order ``k`` (``v >= 0``): let
``q = v >> k`` and ``L`` its bit length (0 for ``q == 0``); the code is ``L``
zeros and a one (the *prefix*), then the ``L - 1`` bits of ``q`` below its
leading one and the ``k`` low bits of ``v`` (the *suffix*):
``L + 1 + max(L - 1, 0) + k`` bits. Written whole, the code of ``v >= 2**k`` is
``v`` itself in ``2 w - k + 2`` bits (``w``: bit length of ``v`` minus one), and
that of ``v < 2**k`` is ``2**k + v`` in ``k + 1`` bits. The layouts write codes
either whole, one after another (``codec_relay``), or by *column*: every prefix
of a column first, then every suffix, so that a reader finds all the prefix
lengths at once (one ``flatnonzero``, or one ``str.find`` per code).

Readers raise only ``RemoteProtocolError(BAD_FRAME)`` (truncated or overlong
codes) and never allocate more than a small multiple of the stream's size.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import overload

import numpy as np
from numpy.typing import NDArray

from posecast.protocol import _accel
from posecast.protocol.errors import ErrorCode, RemoteProtocolError

__all__ = [
    "EG_TABLES",
    "MAX_EG_BITS",
    "MAX_K",
    "SMALL",
    "BitReader",
    "BitWriter",
    "IntReader",
    "IntWriter",
    "best_k",
    "best_k_small",
    "bit_length",
    "eg_code",
    "eg_cost",
    "eg_pack",
    "k_of_histogram",
    "unzz",
    "zz",
]

I64 = NDArray[np.int64]
U64 = NDArray[np.uint64]

#: Largest Exp-Golomb order a frame may state (a 4-bit field).
MAX_K = 15
#: Longest value an Exp-Golomb code may carry, in bits (prefix length + k).
MAX_EG_BITS = 48

# --------------------------------------------------------------------------- zigzag

# The pure hot loops (POSECAST_PURE=1) call these per value rather than inline the
# expression. Against an import-time rewrite that inlines every call (CPU time,
# median of 11 alternating runs, load ~2.5 on 2 cores), the calls cost 1.7 % of a
# compact update encode, 1.9 % of its decode, 2.5 % of a relay snapshot encode and
# 2.5 % of its decode (10 users x 3 streams, 206 calls a snapshot, ~45 ns a call);
# sessions ranged 0.3-3.0 % (encodes) and 1.1-5.5 % (decodes). That is under the
# ~3 % at which a faster shared form would pay (e.g. a ``signed`` flag on
# IntReader.eg, which would save at most that, less a branch on every unsigned
# read); an inlined copy elsewhere would break "zigzag in one module". The calls stay.


@overload
def zz(v: int) -> int: ...
@overload
def zz(v: I64) -> I64: ...
def zz(v: int | I64) -> int | I64:
    """Signed to unsigned: 0, -1, 1, -2 -> 0, 1, 2, 3; a Python int or each value of
    an int64 array. Exact for -2**63 <= v < 2**63, the range of every coded field."""
    return (v << 1) ^ (v >> 63)


@overload
def unzz(z: int) -> int: ...
@overload
def unzz(z: I64) -> I64: ...
@overload
def unzz(z: U64) -> U64: ...
def unzz(z: int | I64 | U64) -> int | I64 | U64:
    """Inverse of :func:`zz`, for a Python int or an int64 array; for a uint64 array
    (zigzag codes of the whole int64 range, e.g. ``zz(v).view(np.uint64)``) the shift
    is logical, so ``unzz(u).view(np.int64)`` gives back every int64 exactly."""
    return (z >> 1) ^ -(z & 1)


# --------------------------------------------------------------------------- Exp-Golomb


def eg_code(v: int, k: int) -> tuple[int, int]:
    """(codeword, length) of ``v >= 0`` in Exp-Golomb of order k, written whole."""
    if v >> k == 0:
        return (1 << k) | v, k + 1
    w = v.bit_length() - 1
    return v, 2 * w - k + 2


#: Values below this have their codes in :data:`EG_TABLES`.
_TABLE_SIZE = 1024
#: ``EG_TABLES[k][v]``: :func:`eg_code` ``(v, k)`` for every v below _TABLE_SIZE.
EG_TABLES = [[eg_code(v, k) for v in range(_TABLE_SIZE)] for k in range(MAX_K + 1)]
#: How far a prefix may run, by order k: at most MAX_EG_BITS - k zeros and a one.
_REACH = [MAX_EG_BITS - k + 1 for k in range(MAX_K + 1)]
_MASK = [(1 << w) - 1 for w in range(MAX_EG_BITS + MAX_K + 1)]
#: By order k and prefix length L: the suffix's (width, leading one, mask). The value
#: is the suffix with the leading one set (L > 0), or the suffix alone (L = 0).
_SUFFIX = [
    [(L - 1 + k, 1 << (L - 1 + k), _MASK[L - 1 + k]) if L else (k, 0, _MASK[k]) for L in range(r)]
    for k, r in enumerate(_REACH)
]


def eg_pack(values: Sequence[int], orders: Sequence[int]) -> tuple[int, int]:
    """(bits, bit count) of the whole codes of ``values[i]`` of order ``orders[i]``,
    one after another (as many values as orders)."""
    fast = _accel.speedups
    if fast is not None:
        got: tuple[int, int] | None = fast.eg_pack(values, orders)
        if got is not None:
            return got
    tables = EG_TABLES
    acc = nbits = 0
    for v, k in zip(values, orders, strict=True):
        if v < _TABLE_SIZE:
            c, w = tables[k][v]
        else:
            c, w = eg_code(v, k)
        acc = (acc << w) | c
        nbits += w
    return acc, nbits


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
    have bit length b) in the fewest bits: see :func:`best_k_small`."""
    n = sum(hist)
    below = 0  # #(b <= k)
    k = 0
    while k < MAX_K:
        below += hist[k]
        if below - (n - below - hist[k + 1]) >= 0:
            break
        k += 1
    return k


def best_k_small(values: Sequence[int]) -> tuple[int, int]:
    """:func:`best_k` of a short column of Python ints, from a histogram of bit lengths.

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
        return best_k_small(v.tolist())
    lengths = bit_length(v[None, :] >> _KS[:, None])
    costs = (2 * lengths + (lengths == 0)).sum(axis=1) + _KS * v.size
    k = int(np.argmin(costs))
    return k, int(costs[k])


#: The name it had before ``best_k_small`` was public.
_best_k_small = best_k_small

# --------------------------------------------------------------------------- Python-int streams


class IntWriter:
    """A bitstream as one Python int: fields and whole codes one at a time, or
    columns (see the module docstring) with the bits each entry ("owner") cost.

    Shifting one growing int costs a copy per field: right for the few hundred
    bits of a relay frame; long frames go through :class:`BitWriter`.
    """

    __slots__ = ("acc", "owned", "total")

    def __init__(self, n: int = 0) -> None:
        self.acc = 0
        self.total = 0
        #: Bits written for each of the entries 0..n-1 (by the column methods).
        self.owned = [0] * n

    def put(self, value: int, width: int) -> None:
        """One field of ``width`` bits (the value must fit)."""
        self.acc = (self.acc << width) | value
        self.total += width

    def eg(self, v: int, k: int) -> None:
        """The whole Exp-Golomb code of order k of ``v``."""
        code, width = eg_code(v, k)
        self.acc = (self.acc << width) | code
        self.total += width

    def fixed(self, values: list[int], width: int, owners: list[int]) -> None:
        """A column: each value in ``width`` bits; ``owners``: the entry of each."""
        col = 0
        for v in values:
            col = (col << width) | v
        self.acc = (self.acc << (width * len(values))) | col
        self.total += width * len(values)
        owned = self.owned
        for o in owners:
            owned[o] += width

    def eg_column(self, values: list[int], k: int, owners: list[int]) -> None:
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
        """The bits, zero-padded to whole bytes."""
        pad = -self.total % 8
        return (self.acc << pad).to_bytes((self.total + pad) // 8, "big")


def _frame_truncated(what: str = "pose frame truncated") -> RemoteProtocolError:
    return RemoteProtocolError(ErrorCode.BAD_FRAME, what)


class IntReader:
    """Reads a bitstream held twice: as one Python int (a field is a shift and a mask)
    and as a string of "0"/"1" (``str.find`` finds the end of a prefix in C).

    Every failure is ``RemoteProtocolError(BAD_FRAME)``: a code or field past the
    end, a prefix longer than ``MAX_EG_BITS - k`` zeros, trailing bits.
    """

    __slots__ = ("pos", "size", "text", "x")

    def __init__(self, body: bytes) -> None:
        self.x = int.from_bytes(body, "big")
        self.size = 8 * len(body)
        self.text = format(self.x, f"0{self.size}b") if body else ""
        self.pos = 0

    @property
    def remaining(self) -> int:
        """Bits not read yet."""
        return self.size - self.pos

    def field(self, width: int) -> int:
        """The next ``width`` bits."""
        end = self.pos + width
        if end > self.size:
            raise _frame_truncated()
        self.pos = end
        return (self.x >> (self.size - end)) & ((1 << width) - 1)

    def fixed(self, n: int, width: int) -> list[int]:
        """A column of ``n`` fields of ``width`` bits."""
        if not n:
            return []
        end = self.pos + n * width
        if end > self.size:
            raise _frame_truncated()
        self.pos = end
        x, size, mask = self.x, self.size, (1 << width) - 1
        return [(x >> (size - p)) & mask for p in range(end - (n - 1) * width, end + 1, width)]

    def eg(self, k: int) -> int:
        """One whole Exp-Golomb code of order k."""
        pos = self.pos
        j = self.text.find("1", pos, pos + _REACH[k])
        if j < 0:
            raise _frame_truncated("pose frame truncated or code too long")
        width, lead, mask = _SUFFIX[k][j - pos]
        end = j + 1 + width
        if end > self.size:
            raise _frame_truncated()
        self.pos = end
        return ((self.x >> (self.size - end)) & mask) | lead

    def eg_column(self, n: int, k: int) -> list[int]:
        """``n`` Exp-Golomb codes of order k: every prefix, then every suffix."""
        find, pos = self.text.find, self.pos
        reach, suffix = _REACH[k], _SUFFIX[k]
        parts = []
        for _ in range(n):
            j = find("1", pos, pos + reach)
            if j < 0:
                raise _frame_truncated("pose frame truncated or code too long")
            parts.append(suffix[j - pos])
            pos = j + 1
        x, size = self.x, self.size
        out = []
        try:
            for width, lead, mask in parts:
                pos += width
                out.append(((x >> (size - pos)) & mask) | lead)
        except ValueError:  # a suffix past the end: a negative shift
            raise _frame_truncated() from None
        self.pos = pos
        return out

    def add_columns(self, jobs: list[tuple[list[list[int]], int, int]]) -> None:
        """For each (rows, c, k), in order: add one signed (zigzag) Exp-Golomb column
        of order k to column c of the rows (one code a row)."""
        for rows, c, k in jobs:
            for row, z in zip(rows, self.eg_column(len(rows), k), strict=True):
                row[c] += unzz(z)

    def rest_is_padding(self) -> bool:
        """Whether only zero padding (fewer than 8 bits) is left."""
        rest = self.size - self.pos
        return rest < 8 and not self.x & ((1 << rest) - 1)

    def finish(self) -> None:
        """Raise unless only zero padding (fewer than 8 bits) is left."""
        if not self.rest_is_padding():
            raise RemoteProtocolError(ErrorCode.BAD_FRAME, "trailing bits in pose frame")


# --------------------------------------------------------------------------- numpy streams


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
