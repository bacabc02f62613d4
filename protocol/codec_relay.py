"""Relay snapshots of the compact codec: encoded once per group, spliced per subscriber.

A relay sends every due subscriber of a room the poses that changed since the
snapshot it last wrote to that subscriber, each coded against the codes that
subscriber holds for the stream (its baseline). Subscribers that hold the same
baselines form a group, and the group's entries are encoded once per tick: this
module's layout (codec version 2) puts each user's entries in one contiguous
run of bits, so the frame of one subscriber, who does not receive its own
streams back, is the group's runs minus its own, joined with a few bits of
user-id gap between them. Splicing costs a few big-int shifts per user, not an
encode per subscriber.

Layout (shares the quantisers and field codings of ``protocol.codec``, version 1;
only the order of the bits differs and the class of an entry)::

    0xC1  flags            bit 1: velocities, bit 2: set (class split), bits 4-7: 2
    uvarint  tick
    svarint  base time, integer microseconds
    uvarint  n_key, uvarint n_delta
    u32 LE   check, iff n_delta > 0: XOR over the delta entries of the CRC-32 of
             (user u16, stream u16, baseline codes int32...) little-endian
    nibbles  Exp-Golomb orders k, 4 bits each, high nibble first, padded to a byte:
             key section (iff n_key):     t_first [vlin vang]
             delta section (iff n_delta): t_first rot0 rot1 pos0 pos1
                                          [vlin0 vlin1 vang0 vang1]
    bits     the key entries, then the delta entries, in (user, stream) order,
             entry by entry; MSB first, zero-padded to a byte

Each entry::

    ug      EG 0       user - previous user (first entry of a section: user;
                       0 continues the previous entry's user)
    sg      EG 0       stream (first entry of a user) or stream - previous - 1
    time    EG k, zz   first entry of a user: ms before the base time (k t_first);
            EG 0, zz   else: offset - previous entry's offset
    key     idx 2 bits; a, b, c 13 bits (+4095); px, py, pz Volume.bits;
            velocities EG zz (k vlin, vang)
    delta   idx EG 0 of (idx - baseline idx) mod 4; a, b, c EG zz of the difference
            to the baseline rotation re-expressed with the new idx (k rot<class>);
            px, py, pz EG zz of the difference (k pos<class>); velocities the same

The class of an entry is 0 for the first entry of its user in the section (the
head, whose stream id a relay allocates first) and 1 for the others. Exp-Golomb
of order k codes v < 2**k as a one and k bits, else as v itself written in
2 w - k + 2 bits, w = bit length of v minus one (the ``protocol.bits`` code).
"""

from __future__ import annotations

import struct
import zlib
from collections import deque
from collections.abc import Mapping, Sequence
from itertools import pairwise
from operator import itemgetter
from typing import Any, NamedTuple, Protocol

from posecast.protocol import _accel
from posecast.protocol.bits import (
    MAX_EG_BITS,
    IntWriter,
    best_k_small,
    eg_code,
    eg_pack,
    k_of_histogram,
    zz,
)
from posecast.protocol.codec_frame import (
    _US_LIMIT,
    CODEC_MAGIC,
    F_VELOCITY,
    _svarint,
    _uvarint,
)
from posecast.protocol.codec_quant import (
    ROTATION_BITS,
    M,
    Volume,
    codes_problem_rows,
    local_error,
)
from posecast.protocol.codec_relay_read import (
    _CHECKS,
    _F_SPLIT,
    _ID_MAX,
    _TIME_MS_LIMIT,
    RELAY_CODEC_VERSION,
    RelayEntry,
    RelaySnapshot,
    Row,
    baseline_check,
    decode_relay_snapshot,
    snapshot_counts,
)
from posecast.protocol.codec_small import predict_row
from posecast.protocol.codec_store import CodeHistory, baseline_of
from posecast.protocol.errors import ErrorCode

__all__ = [
    "RELAY_CODEC_VERSION",
    "GroupSnapshot",
    "RelayEntry",
    "RelaySnapshot",
    "StoredStream",
    "baseline_check",
    "decode_relay_snapshot",
    "encode_group",
    "encode_stored",
    "snapshot_counts",
]


class _Block(NamedTuple):
    """One user's entries in one section, without the leading user gap."""

    user: int
    n: int
    bits: int
    nbits: int
    check: int


class _Spliced:
    """One section's blocks joined with their user gaps, with the joins of every prefix
    and suffix, so that the section without one user's block is a few big-int shifts
    (the user after it gets a new gap), not a join of every block."""

    __slots__ = ("blocks", "check", "index", "n", "prefix", "suffix")

    def __init__(self, blocks: list[_Block]) -> None:
        self.blocks = blocks
        self.index = {b.user: j for j, b in enumerate(blocks)}
        #: prefix[j]: (bits, bit count) of blocks[:j]; suffix[j]: of blocks[j:].
        self.prefix = [(0, 0)]
        acc = nbits = n = check = prev = 0
        for b in blocks:
            code, width = eg_code(b.user - prev, 0)
            acc = (((acc << width) | code) << b.nbits) | b.bits
            nbits += width + b.nbits
            self.prefix.append((acc, nbits))
            n += b.n
            check ^= b.check
            prev = b.user
        self.n, self.check = n, check
        self.suffix = [(0, 0)] * (len(blocks) + 1)
        acc = nbits = 0
        for j in range(len(blocks) - 1, -1, -1):
            b = blocks[j]
            code, width = eg_code(b.user - (blocks[j - 1].user if j else 0), 0)
            acc |= ((code << b.nbits) | b.bits) << nbits
            nbits += width + b.nbits
            self.suffix[j] = (acc, nbits)

    def without(self, user: int | None) -> tuple[int, int, int, int]:
        """(bits, bit count, entries, check) of the section without ``user``'s block."""
        j = self.index.get(user) if user is not None else None
        if j is None:
            acc, nbits = self.prefix[-1]
            return acc, nbits, self.n, self.check
        blocks = self.blocks
        acc, nbits = self.prefix[j]
        if j + 1 < len(blocks):
            b = blocks[j + 1]
            code, width = eg_code(b.user - (blocks[j - 1].user if j else 0), 0)
            rest, rest_bits = self.suffix[j + 2]
            acc = (((((acc << width) | code) << b.nbits) | b.bits) << rest_bits) | rest
            nbits += width + b.nbits + rest_bits
        return acc, nbits, self.n - blocks[j].n, self.check ^ blocks[j].check


class GroupSnapshot:
    """A group's snapshot, encoded once; :meth:`frame` splices one subscriber's bytes."""

    __slots__ = (
        "_delta",
        "_head",
        "_key",
        "_nibbles",
        "_orders",
        "_packed",
        "_spliced",
        "base_time",
        "tick",
    )

    def __init__(
        self,
        tick: int,
        base_us: int,
        velocity: bool,
        key: list[_Block],
        delta: list[_Block],
        nibbles: tuple[list[int], list[int]],
    ) -> None:
        self.tick = tick
        self.base_time = base_us / 1e6
        flags = (F_VELOCITY if velocity else 0) | _F_SPLIT | (RELAY_CODEC_VERSION << 4)
        self._head = bytes([CODEC_MAGIC, flags]) + _uvarint(tick) + _svarint(base_us)
        self._key = key
        self._delta = delta
        self._nibbles = nibbles
        #: The sections prepared for splicing, made at the second frame asked for (a
        #: group of one subscriber never needs them).
        self._spliced: tuple[_Spliced, _Spliced] | None = None
        #: The nibble bytes of the orders, by (any key entry, any delta entry).
        self._orders: dict[tuple[bool, bool], bytes] = {}
        #: (compiled module, its packed blocks) of a group the accelerator encoded
        #: (``key`` and ``delta`` are then empty): only that module splices them.
        self._packed: tuple[Any, bytes] | None = None

    @classmethod
    def _compiled(
        cls,
        tick: int,
        base_us: int,
        velocity: bool,
        fast: Any,
        packed: bytes,
        nibbles: tuple[list[int], list[int]],
    ) -> GroupSnapshot:
        """A group encoded by the accelerator (``_speedups.encode_group``)."""
        group = cls(tick, base_us, velocity, [], [], nibbles)
        group._packed = (fast, packed)
        return group

    @property
    def users(self) -> list[int]:
        """Every user with an entry in this snapshot."""
        if self._packed is not None:
            packed = self._packed[1]
            (count,) = struct.unpack_from("<q", packed)
            return sorted(
                {u for (u, *_) in struct.iter_unpack("<iiiIqq", packed[8 : 8 + 32 * count])}
            )
        return sorted({b.user for b in self._key} | {b.user for b in self._delta})

    def frame(self, exclude: int | None = None) -> tuple[bytes, int]:
        """The bytes for a subscriber that does not receive ``exclude``'s streams,
        and how many entries they hold (0: nothing to send, and ``b""``)."""
        if self._packed is not None:
            module, packed = self._packed
            out: tuple[bytes, int] = module.splice_packed(
                self._head, packed, *self._nibbles, -1 if exclude is None else exclude
            )
            return out
        fast = _accel.speedups
        if fast is not None:
            got: tuple[bytes, int] = fast.splice(
                self._head,
                self._key,
                self._delta,
                *self._nibbles,
                -1 if exclude is None else exclude,
            )
            return got
        spliced = self._spliced
        if spliced is None:
            self._spliced = (_Spliced(self._key), _Spliced(self._delta))
            return self._frame_joined(exclude)
        kacc, kbits, nk, _ = spliced[0].without(exclude)
        dacc, dbits, nd, check = spliced[1].without(exclude)
        return self._bytes(nk, nd, check, (kacc << dbits) | dacc, kbits + dbits)

    def _frame_joined(self, exclude: int | None) -> tuple[bytes, int]:
        """:meth:`frame` by joining every block (the first frame of a group)."""
        if self._packed is not None:
            return self.frame(exclude)
        acc = nbits = check = 0
        counts = [0, 0]
        for section, blocks in enumerate((self._key, self._delta)):
            prev = 0
            for b in blocks:
                if b.user == exclude:
                    continue
                code, width = eg_code(b.user - prev, 0)
                acc = (((acc << width) | code) << b.nbits) | b.bits
                nbits += width + b.nbits
                counts[section] += b.n
                check ^= b.check
                prev = b.user
        return self._bytes(counts[0], counts[1], check, acc, nbits)

    def _bytes(self, nk: int, nd: int, check: int, acc: int, nbits: int) -> tuple[bytes, int]:
        if not nk + nd:
            return b"", 0
        orders = self._orders.get((nk > 0, nd > 0))
        if orders is None:
            nib = (self._nibbles[0] if nk else []) + (self._nibbles[1] if nd else [])
            if len(nib) % 2:
                nib.append(0)
            orders = bytes((a << 4) | c for a, c in zip(nib[::2], nib[1::2], strict=True))
            self._orders[(nk > 0, nd > 0)] = orders
        pad = -nbits % 8
        return (
            self._head
            + _uvarint(nk)
            + _uvarint(nd)
            + (check.to_bytes(4, "little") if nd else b"")
            + orders
            + (acc << pad).to_bytes((nbits + pad) // 8, "big"),
            nk + nd,
        )


def _offsets(entries: list[RelayEntry], base: float) -> list[int]:
    out = []
    for e in entries:
        t = e[2]
        o = round((base - t) * 1000.0) if t == t and abs(t) < 1e12 else _TIME_MS_LIMIT
        if abs(o) >= _TIME_MS_LIMIT:
            raise local_error(ErrorCode.BAD_MESSAGE, "capture time too far from the base time")
        out.append(o)
    return out


def _by_user(entries: list[RelayEntry]) -> list[list[int]]:
    """Indices of ``entries`` (sorted) grouped by user."""
    groups: list[list[int]] = []
    prev = -1
    for i, e in enumerate(entries):
        if e[0] != prev:
            groups.append([])
            prev = e[0]
        groups[-1].append(i)
    return groups


def _time_fields(
    entries: list[RelayEntry], off: list[int], groups: list[list[int]]
) -> tuple[int, list[tuple[int, int]]]:
    """k of t_first, and per entry (sg, time code) before Exp-Golomb."""
    fields: list[tuple[int, int]] = [(0, 0)] * len(entries)
    firsts = []
    for g in groups:
        i0 = g[0]
        fields[i0] = (entries[i0][1], zz(off[i0]))
        firsts.append(fields[i0][1])
        for a, b in pairwise(g):
            fields[b] = (entries[b][1] - entries[a][1] - 1, zz(off[b] - off[a]))
    return best_k_small(firsts)[0], fields


def _key_blocks(
    entries: list[RelayEntry], base: float, volume: Volume, velocity: bool
) -> tuple[list[_Block], list[int]]:
    if not entries:
        return [], []
    off = _offsets(entries, base)
    groups = _by_user(entries)
    kt, fields = _time_fields(entries, off, groups)
    nib = [kt]
    kv = (0, 0)
    if velocity:
        lin = [zz(v) for e in entries for v in e[3][7:10]]
        ang = [zz(v) for e in entries for v in e[3][10:13]]
        kv = (best_k_small(lin)[0], best_k_small(ang)[0])
        nib += list(kv)
    bx, by, bz = volume.bits
    blocks = []
    for g in groups:
        w = IntWriter()
        for j, i in enumerate(g):
            sg, tz = fields[i]
            if j:
                w.put(1, 1)
            w.eg(sg, 0)
            w.eg(tz, kt if j == 0 else 0)
            r = entries[i][3]
            w.put(
                (
                    (
                        (
                            (
                                (((r[0] << 13 | (r[1] + M)) << 13 | (r[2] + M)) << 13 | (r[3] + M))
                                << bx
                            )
                            | r[4]
                        )
                        << by
                        | r[5]
                    )
                    << bz
                )
                | r[6],
                2 + 3 * ROTATION_BITS + bx + by + bz,
            )
            if velocity:
                for c in range(7, 13):
                    w.eg(zz(r[c]), kv[0] if c < 10 else kv[1])
        blocks.append(_Block(entries[g[0]][0], len(g), w.acc, w.total, 0))
    return blocks, nib


def _delta_values(
    entries: list[RelayEntry],
    groups: list[list[int]],
    fields: list[tuple[int, int]],
    width: int,
) -> tuple[list[list[int]], list[int], list[list[list[int]]]]:
    """Per user: the values its block codes, in order (per entry: ug = 0 but for the
    user's first, sg, time code, idx step, then the zigzagged differences, 3 per column
    group); per user its share of the check; and per (column group, class) a histogram
    of the differences' bit lengths, from which the Exp-Golomb order of each is chosen
    (see ``bits._best_k_small``)."""
    hists = [[[0] * (MAX_EG_BITS + 2) for _ in range(2)] for _ in range((width - 1) // 3)]
    (rot0, rot1), (pos0, pos1) = hists[0], hists[1]
    pack = _CHECKS[width].pack
    values: list[list[int]] = []
    checks: list[int] = []
    for g in groups:
        cls, hr, hp = 0, rot0, pos0
        row: list[int] = []
        check = 0
        user = entries[g[0]][0]
        for i in g:
            e = entries[i]
            r, b = e[3], e[4]
            assert b is not None
            if r[0] == b[0]:
                p0, p1, p2 = b[1], b[2], b[3]
            else:
                p0, p1, p2 = predict_row(b, r[0])
            z0, z1, z2 = zz(r[1] - p0), zz(r[2] - p1), zz(r[3] - p2)
            z3, z4, z5 = zz(r[4] - b[4]), zz(r[5] - b[5]), zz(r[6] - b[6])
            hr[z0.bit_length()] += 1
            hr[z1.bit_length()] += 1
            hr[z2.bit_length()] += 1
            hp[z3.bit_length()] += 1
            hp[z4.bit_length()] += 1
            hp[z5.bit_length()] += 1
            if cls:
                row.append(0)  # ug: the same user
            row += (*fields[i], (r[0] - b[0]) & 3, z0, z1, z2, z3, z4, z5)
            for c in range(7, width):
                z = zz(r[c] - b[c])
                row.append(z)
                hists[(c - 1) // 3][cls][z.bit_length()] += 1
            check ^= zlib.crc32(pack(user, e[1], *b))
            cls, hr, hp = 1, rot1, pos1
        values.append(row)
        checks.append(check)
    return values, checks, hists


def _delta_blocks(
    entries: list[RelayEntry], base: float, velocity: bool
) -> tuple[list[_Block], list[int]]:
    if not entries:
        return [], []
    fast = _accel.speedups
    if fast is not None:
        got = fast.delta_blocks(entries, base, velocity)
        if got is not None:
            return [_Block(*b) for b in got[0]], got[1]
    off = _offsets(entries, base)
    groups = _by_user(entries)
    kt, fields = _time_fields(entries, off, groups)
    width = 13 if velocity else 7
    values, checks, hists = _delta_values(entries, groups, fields, width)
    ks = [[k_of_histogram(h) for h in pair] for pair in hists]
    nib = [kt] + [k for pair in ks for k in pair]
    # The orders of a user's first entry's values (sg, time, idx step, differences),
    # and of its other entries' (ug first).
    first = (0, kt, 0, *(ks[f // 3][0] for f in range(width - 1)))
    other = (0, 0, 0, 0, *(ks[f // 3][1] for f in range(width - 1)))
    orders: dict[int, tuple[int, ...]] = {}
    blocks = []
    for g, vals, check in zip(groups, values, checks, strict=True):
        order = orders.get(len(g))
        if order is None:
            order = orders[len(g)] = first + other * (len(g) - 1)
        acc, nbits = eg_pack(vals, order)
        blocks.append(_Block(entries[g[0]][0], len(g), acc, nbits, check))
    return blocks, nib


class StoredStream(Protocol):
    """A relay's stored stream as :func:`encode_stored` reads it."""

    user: int
    #: Capture time of its newest pose, and the store version it was stored at.
    capture: float
    version: int
    #: Codes of that pose, or None until :meth:`coded` computes them.
    codes: Row | None

    @property
    def history(self) -> deque[tuple[int, Row]] | CodeHistory:
        """(version, codes) of the versions coded so far, oldest first: a deque, or a
        ``codec_store.CodeHistory`` (the accelerator reads and writes its bytes)."""
        ...

    def coded(self, volume: Volume) -> Row:
        """The newest version's codes (computed once), remembered in ``history``.

        With ``codes`` set (a list) this must be ``history.append((version, codes))``
        unless the newest in ``history`` is that version already, then ``codes``: the
        accelerator does just that itself rather than call it."""
        ...


def encode_stored(
    tick: int,
    base_time: float,
    streams: Mapping[int, StoredStream],
    since: int,
    volume: Volume,
    velocity: bool = False,
) -> GroupSnapshot | None:
    """:func:`encode_group` (trusted) of the streams stored after version ``since``, each
    coded against its codes as of ``since`` (the newest of its ``history`` at or before
    it: what a subscriber whose last snapshot covered ``since`` holds) or absolute if it
    has none then or ``since < 0``; None if no stream is newer than ``since``.

    A relay's group snapshot in one call; the accelerator reads the store itself.
    """
    fast = _accel.speedups
    if fast is not None and type(streams) is dict:
        base_us = _base_us(tick, base_time)
        got = fast.encode_stored(streams, since, volume, base_us, velocity, volume.bits)
        if got is False:
            return None
        if got is not None:
            return GroupSnapshot._compiled(tick, base_us, velocity, fast, got[0], (got[1], got[2]))
    width = 13 if velocity else 7
    entries: list[RelayEntry] = []
    for sid, s in streams.items():
        if s.version <= since:
            continue
        row = s.coded(volume)
        base = baseline_of(s.history, since) if since >= 0 else None
        entries.append(
            (s.user, sid, s.capture, row[:width], None if base is None else base[:width])
        )
    if not entries:
        return None
    return encode_group(tick, base_time, entries, volume, velocity, trusted=True)


def _base_us(tick: int, base_time: float) -> int:
    """The base time in integer microseconds; raises for it or the tick out of range."""
    if not 0 <= tick < 1 << 63:
        raise local_error(ErrorCode.BAD_MESSAGE, "tick out of range")
    base_us = round(base_time * 1e6) if base_time == base_time else _US_LIMIT
    if abs(base_us) >= _US_LIMIT:
        raise local_error(ErrorCode.BAD_MESSAGE, "base time out of range")
    return base_us


def encode_group(
    tick: int,
    base_time: float,
    entries: Sequence[RelayEntry],
    volume: Volume,
    velocity: bool = False,
    *,
    trusted: bool = False,
) -> GroupSnapshot:
    """Encode a group's entries once (any order; one per (user, stream)).

    An entry with a baseline is delta-coded against it, one without goes absolute.
    Codes are rows of Python ints. Raises ``LocalProtocolError`` for ids, times or
    codes out of range; ``trusted`` skips the range checks of the codes (a relay's
    codes come from its own quantiser or decoder, which checked them).
    """
    base_us = _base_us(tick, base_time)
    base = base_us / 1e6
    fast = _accel.speedups
    if trusted and fast is not None and type(entries) is list:
        # Sorting, the id checks and both sections in one call; None where the
        # checks below would raise (they do) or the pure path decide otherwise.
        got = fast.encode_group(entries, base_us, velocity, volume.bits)
        if got is not None:
            return GroupSnapshot._compiled(tick, base_us, velocity, fast, got[0], (got[1], got[2]))
        fast = None
    width = 13 if velocity else 7
    ordered = sorted(entries, key=itemgetter(0, 1))
    previous = None
    for e in ordered:
        name = e[0], e[1]
        if not (0 <= name[0] <= _ID_MAX and 0 <= name[1] <= _ID_MAX):
            raise local_error(ErrorCode.BAD_MESSAGE, "user or stream id out of range")
        if name == previous:  # sorted: a stream's twin is next to it
            raise local_error(ErrorCode.BAD_MESSAGE, f"stream {e[1]} of user {e[0]} twice")
        previous = name
        if len(e[3]) != width or (e[4] is not None and len(e[4]) != width):
            raise local_error(ErrorCode.BAD_MESSAGE, f"codes must be rows of {width}")
        if not trusted:
            problem = codes_problem_rows([e[3]] if e[4] is None else [e[3], e[4]], volume)
            if problem:
                raise local_error(ErrorCode.BAD_POSE, problem)
    if fast is not None:
        got = fast.encode_group(ordered, base_us, velocity, volume.bits)
        if got is not None:
            return GroupSnapshot._compiled(tick, base_us, velocity, fast, got[0], (got[1], got[2]))
    key, knib = _key_blocks([e for e in ordered if e[4] is None], base, volume, velocity)
    delta, dnib = _delta_blocks([e for e in ordered if e[4] is not None], base, velocity)
    return GroupSnapshot(tick, base_us, velocity, key, delta, (knib, dnib))
