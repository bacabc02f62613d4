"""Pose message layout version 2: a group of compact updates, delta-coded, in one message.

A client that joined with the compact codec sends quantised *codes*
(``protocol.codec``); the relay relays ``dequantise(codes)`` as float32. The
recorder keeps those codes instead of the floats: the writer thread collects the
compact updates of a chunk and writes them as one ``poses`` message (layout 2)
just before the chunk closes (or sooner: see ``GROUP_SPAN_MAX`` and
``GROUP_UPDATES_MAX``). Each message is self-contained (its first update of each
stream is coded absolutely), so a lost chunk or message breaks nothing else.

Layout 2 (little-endian)::

    offset  type      field
    0       u8        layout version (2)
    1       u8        flags (bit 0: velocities: 13 codes an entry, else 7)
    2       u32       m: updates
    6       u32       k: entries (poses) of all updates
    10      f64[6]    room volume: lo x y z, hi x y z
    58      u64       the first update's arrival time, ns (``to_ns``)
    66      u32       CRC-32 of the bytes before this field, then of those after it
    70      columns   each: u8 width w (1, 2, 4 or 8), then w byte planes of the
                      column's values as unsigned w-byte integers (plane b holds
                      byte b of every value)

Columns, in order (zz: zigzag of a signed difference):

- per update (m values): user; n (entries); zz(seq - the same user's previous
  seq in the message, the first: the seq itself); zz(base time in whole us -
  the same user's previous, the first: itself); zz(arrival ns - the previous
  update's, the first: 0); zz(arrival bits - bits of ``arrival_ns / 1e9``) (the
  arrival time exactly; the server's clock counts whole ns, so mostly 0);
- per entry (k values): stream id, update by update; then, with the entries
  ordered by (user, stream) (stable: each stream's entries in update order),
  the bits of ``dt`` (float32 capture time - base time, as the relay holds it)
  and one column per code (7 or 13): zz(code - the same stream's previous code
  in the message, the first: the code itself). Stream by stream, the
  differences of one stream sit together, which the compressor rewards.

Decoding gives back, bit for bit, what a layout 1 message of the same update
holds: capture time ``float64(dt) + base_us / 1e6``, the poses
``dequantise(codes, volume)`` (float32) and velocities as float16. The writer
checks that identity for every update before it codes it (an update that
fails, e.g. whose base time is not whole microseconds, is written as layout 1).
The byte planes are left to the chunk's zstd, which squeezes the high planes of
small differences to almost nothing.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Final

import numpy as np
from numpy.typing import NDArray

from posecast.protocol.bits import unzz, zz
from posecast.protocol.codec import Volume, dequantise
from posecast.protocol.codec_quant import codes_problem
from posecast.protocol.poses import PoseUpdate
from posecast.recorder.format import FormatError, PoseRecord, encode_pose, to_ns, to_ns_many

__all__ = [
    "COMPACT_VERSION",
    "GROUP_SPAN_MAX",
    "GROUP_UPDATES_MAX",
    "CompactUpdate",
    "compact_update",
    "decode_group",
    "encode_group",
    "expand_group",
    "is_group",
]

COMPACT_VERSION: Final = 2
#: A message holds updates that arrived within this many seconds of its first
#: (readers widen a time range by it), and at most this many updates.
GROUP_SPAN_MAX: Final = 2.0
GROUP_UPDATES_MAX: Final = 16384
_VELOCITY: Final = 1
_HEAD: Final = struct.Struct("<BBII6dQI")
_CRC_AT: Final = _HEAD.size - 4
_WIDTHS: Final = (1, 2, 4, 8)
_U64 = np.dtype("<u8")


@dataclass(frozen=True, eq=False)
class CompactUpdate:
    """One compact pose update as the relay took it: what layout 2 codes.

    ``streams`` (n,) u16, ``dt`` (n,) float32 (capture - base), ``codes`` (n, 7
    or 13) int64 (the codes the relay dequantised), ``poses`` (n, 7) float32 and
    ``velocities`` (n, 6) float16 or None: what the relay relayed (checked
    against the codes when coded).
    """

    user: int
    seq: int
    arrival: float
    base_time: float
    streams: NDArray[np.uint16]
    dt: NDArray[np.float32]
    codes: NDArray[np.int64]
    poses: NDArray[np.float32]
    velocities: NDArray[np.float16] | None
    volume: Volume

    def __len__(self) -> int:
        """About the bytes it takes in a message (for the chunk size bound)."""
        return 8 + 12 * len(self.streams)

    @property
    def velocity(self) -> bool:
        return int(self.codes.shape[1]) == 13

    def record(self) -> PoseRecord:
        """The update as a layout 1 record holds it."""
        caps = self.dt.astype(np.float64) + self.base_time
        return PoseRecord(
            self.user, self.seq, self.arrival, self.streams, caps, self.poses, self.velocities
        )


def compact_update(
    user: int,
    arrival: float,
    update: PoseUpdate,
    codes: Mapping[int, Sequence[int]],
    volume: Volume,
    base_time: float | None = None,
) -> CompactUpdate | None:
    """The :class:`CompactUpdate` of a relayed update and its codes (stream id -> row).

    ``None`` if the codes do not name exactly the update's streams (then the
    update is recorded as layout 1).
    """
    entries = update.entries
    streams = entries["stream"]
    ids = streams.tolist()
    if len(codes) != len(ids):
        return None
    try:
        rows = list(codes.values()) if list(codes) == ids else [codes[s] for s in ids]
        array = np.array(rows, np.int64).reshape(len(ids), -1)
    except (KeyError, ValueError):
        return None
    names = entries.dtype.names or ()
    return CompactUpdate(
        user,
        update.seq,
        arrival,
        update.base_time if base_time is None else base_time,
        streams,
        entries["dt"],
        array,
        entries["pose"],
        entries["velocity"] if "velocity" in names else None,
        volume,
    )


def newest_ns(update: CompactUpdate) -> int:
    """The publish time of the update's layout 1 record: its newest capture, in ns."""
    if not len(update.streams):
        return to_ns(update.arrival)
    return to_ns(float(update.dt.max()) + update.base_time)


def _zz(v: NDArray[np.int64]) -> NDArray[np.uint64]:
    return zz(v).view(_U64)


def _unzz(u: NDArray[np.uint64]) -> NDArray[np.int64]:
    return unzz(u).view(np.int64)


def _column(values: NDArray[np.uint64]) -> bytes:
    top = int(values.max()) if len(values) else 0
    w = next(w for w in _WIDTHS if top < 1 << (8 * w))
    planes = values.astype(f"<u{w}").view(np.uint8).reshape(len(values), w).T
    return bytes([w]) + planes.tobytes()


def _segment_deltas(
    keys: NDArray[np.int64], values: NDArray[np.int64], by_key: bool = False
) -> NDArray[np.int64]:
    """Each value minus the previous one of the same key (the first of a key: itself).

    In the order of ``values``, or (``by_key``) ordered by key, stably.
    """
    order = np.argsort(keys, kind="stable")
    v = values[order]
    d = v.copy()
    same = keys[order][1:] == keys[order][:-1]
    d[1:][same] = v[1:][same] - v[:-1][same]
    if by_key:
        return d
    out = np.empty_like(d)
    out[order] = d
    return out


def _segment_sums(
    keys: NDArray[np.int64], deltas: NDArray[np.int64], by_key: bool = False
) -> NDArray[np.int64]:
    """The inverse of :func:`_segment_deltas` (wrapping int64 arithmetic)."""
    order = np.argsort(keys, kind="stable")
    d = deltas if by_key else deltas[order]
    with np.errstate(over="ignore"):
        total = np.cumsum(d, axis=0)
        starts = np.ones(len(d), bool)
        starts[1:] = keys[order][1:] != keys[order][:-1]
        seg = np.cumsum(starts) - 1
        before = (total - d)[starts]
        v = total - before[seg]
    out: NDArray[np.int64] = np.empty_like(v)
    out[order] = v
    return out


def _ns_seconds(ns: NDArray[np.uint64]) -> NDArray[np.float64]:
    """Seconds of ns counts: what the arrival residual is taken against (both ends)."""
    out: NDArray[np.float64] = ns.astype(np.float64) / 1e9
    return out


def _plausible(update: CompactUpdate, first: CompactUpdate) -> bool:
    """The cheap checks: whole-us base time, the codes' shape, the group's volume and variant."""
    base_us = round(update.base_time * 1e6)
    if base_us / 1e6 != update.base_time or abs(base_us) >= 1 << 62:
        return False
    n = len(update.streams)
    width = 13 if update.velocities is not None else 7
    if update.codes.shape != (n, width) or width != (13 if first.velocity else 7):
        return False
    return update.volume == first.volume


def _exact(updates: Sequence[CompactUpdate]) -> list[CompactUpdate]:
    """The updates whose codes decode, in one message with each other, to exactly the
    floats the relay relayed (dequantised together, as the reader will)."""
    good = [u for u in updates if _plausible(u, updates[0])]
    if not good:
        return good
    codes = np.concatenate([u.codes for u in good]).astype(np.int64)
    if not len(codes):
        return good
    if codes_problem(codes, good[0].volume) is not None:  # find whose codes are out of range
        kept = [u for u in good if codes_problem(u.codes, u.volume) is None]
        return _exact(kept) if len(kept) < len(good) else []
    poses, vel = dequantise(codes, good[0].volume)
    relayed = np.concatenate([u.poses for u in good]).astype("<f4")
    rows = (poses.view("<u4") == relayed.view("<u4")).all(axis=1)
    if vel is not None:
        mine = vel.astype("<f2").view("<u2")
        theirs = np.concatenate([u.velocities for u in good if u.velocities is not None])
        rows &= (mine == theirs.astype("<f2").view("<u2")).all(axis=1)
    if bool(rows.all()):
        return good
    ends = np.cumsum([len(u.streams) for u in good])
    ok = [
        bool(rows[e - len(u.streams) : e].all()) for u, e in zip(good, ends.tolist(), strict=True)
    ]
    # the rest is dequantised again without them: check that batch too
    return _exact([u for u, k in zip(good, ok, strict=True) if k])


def encode_group(updates: Sequence[CompactUpdate]) -> tuple[bytes | None, list[CompactUpdate]]:
    """One layout 2 message of the updates that code exactly, and those that do not.

    Updates of another volume or variant than the first (the writer groups them
    so there are none) are among those that do not. The message is ``None`` if
    no update codes exactly.
    """
    good = _exact(updates) if updates else []
    kept = {id(u) for u in good}
    bad = [u for u in updates if id(u) not in kept]
    if not good:
        return None, bad
    volume = good[0].volume
    width = good[0].codes.shape[1]
    m = len(good)
    users = np.array([u.user for u in good], np.int64)
    ns = np.array([len(u.streams) for u in good], np.int64)
    seqs = np.array([u.seq for u in good], np.uint64).view(np.int64)
    bases = np.array([round(u.base_time * 1e6) for u in good], np.int64)
    arrivals = np.array([u.arrival for u in good], "<f8")
    arrival_ns = np.array(to_ns_many(arrivals), _U64)
    arrival_d = np.zeros(m, _U64)
    arrival_d[1:] = arrival_ns[1:] - arrival_ns[:-1]
    residual = arrivals.view(_U64) - _ns_seconds(arrival_ns).view(_U64)
    streams = np.concatenate([u.streams for u in good]).astype(np.int64)
    dt = np.concatenate([u.dt for u in good]).astype("<f4").view("<u4").astype(np.int64)
    codes = np.concatenate([u.codes for u in good]).astype(np.int64)
    keys = (np.repeat(users, ns) << 16) | streams
    with np.errstate(over="ignore"):
        dcodes = _segment_deltas(keys, codes, by_key=True)
        dt = dt[np.argsort(keys, kind="stable")]
        dseq = _segment_deltas(users, seqs)
        dbase = _segment_deltas(users, bases)
    columns = [
        users.view(_U64),
        ns.view(_U64),
        _zz(dseq),
        _zz(dbase),
        _zz(arrival_d.view(np.int64)),
        _zz(residual.view(np.int64)),
        streams.view(_U64),
        dt.view(_U64),
        *(_zz(np.ascontiguousarray(dcodes[:, j])) for j in range(width)),
    ]
    body = b"".join(_column(c) for c in columns)
    flags = _VELOCITY if width == 13 else 0
    head = _HEAD.pack(
        COMPACT_VERSION, flags, m, len(streams), *volume.lo, *volume.hi, int(arrival_ns[0]), 0
    )
    crc = zlib.crc32(body, zlib.crc32(head[:_CRC_AT]))
    return head[:_CRC_AT] + struct.pack("<I", crc) + body, bad


class _Cursor:
    def __init__(self, data: bytes) -> None:
        self.data = data
        self.at = _HEAD.size

    def column(self, count: int) -> NDArray[np.uint64]:
        data, at = self.data, self.at
        if at >= len(data):
            raise FormatError("compact pose message ends before its columns do")
        w = data[at]
        if w not in _WIDTHS:
            raise FormatError(f"compact pose message has a column of width {w}")
        end = at + 1 + w * count
        if end > len(data):
            raise FormatError("compact pose message is cut short inside a column")
        planes = np.frombuffer(data, np.uint8, w * count, at + 1).reshape(w, count)
        self.at = end
        return np.ascontiguousarray(planes.T).view(f"<u{w}").reshape(count).astype(_U64)


def decode_group(data: bytes | bytearray | memoryview) -> list[PoseRecord]:
    """The updates of a layout 2 message, as layout 1 records of them (bit-exact).

    Raises :class:`FormatError` on any message that is not exactly a valid
    layout 2 message (truncated, trailing bytes, CRC mismatch, codes out of range).
    """
    data = bytes(data)
    if len(data) < _HEAD.size:
        raise FormatError(f"compact pose message of {len(data)} bytes is shorter than its header")
    version, flags, m, k, *rest = _HEAD.unpack_from(data, 0)
    lo, hi, first_arrival, crc = rest[0:3], rest[3:6], rest[6], rest[7]
    if version != COMPACT_VERSION:
        raise FormatError(f"unknown pose layout version {version}")
    if flags & ~_VELOCITY:
        raise FormatError(f"unknown compact pose message flags {flags:#04x}")
    if zlib.crc32(data[_HEAD.size :], zlib.crc32(data[:_CRC_AT])) != crc:
        raise FormatError("compact pose message fails its CRC (corrupt)")
    width = 13 if flags & _VELOCITY else 7
    # every value takes at least a byte: refuse counts the message cannot hold
    if 5 * m + (2 + width) * k > len(data):
        raise FormatError("compact pose message counts exceed its size")
    try:
        volume = Volume((lo[0], lo[1], lo[2]), (hi[0], hi[1], hi[2]))
    except ValueError as exc:
        raise FormatError(f"compact pose message has a bad volume: {exc}") from None
    cur = _Cursor(data)
    users = cur.column(m).astype(np.int64)
    ns = cur.column(m).astype(np.int64)
    dseq = _unzz(cur.column(m))
    dbase = _unzz(cur.column(m))
    arrival_d = _unzz(cur.column(m)).view(_U64)
    residual = _unzz(cur.column(m)).view(_U64)
    if int(ns.sum()) != k or (m and (int(users.max()) > 0xFFFF or int(ns.max()) > 0xFFFF)):
        raise FormatError("compact pose message: entry counts do not add up")
    streams = cur.column(k).astype(np.int64)
    dt_bits = cur.column(k)
    dcodes = np.stack([_unzz(cur.column(k)) for _ in range(width)], axis=1) if k else None
    if cur.at != len(data):
        raise FormatError("compact pose message has trailing bytes")
    if (k and int(streams.max()) > 0xFFFF) or (k and int(dt_bits.max()) > 0xFFFFFFFF):
        raise FormatError("compact pose message: stream id or time out of range")
    seqs = _segment_sums(users, dseq)
    bases = _segment_sums(users, dbase)
    if m and int(np.abs(bases).max()) >= 1 << 62:
        raise FormatError("compact pose message: base time out of range")
    with np.errstate(over="ignore"):
        arrival_ns = np.cumsum(arrival_d, dtype=_U64) + np.uint64(first_arrival)
        arrivals = (_ns_seconds(arrival_ns).view(_U64) + residual).view("<f8")
    if dcodes is not None:
        keys = (np.repeat(users, ns) << 16) | streams
        codes = _segment_sums(keys, dcodes, by_key=True)
        unsorted = np.empty_like(dt_bits)
        unsorted[np.argsort(keys, kind="stable")] = dt_bits
        dt_bits = unsorted
        problem = codes_problem(codes, volume)
        if problem is not None:
            raise FormatError(f"compact pose message: {problem}")
        poses, vel = dequantise(codes, volume)
    else:
        poses, vel = np.zeros((0, 7), np.float32), np.zeros((0, 6), np.float32)
    dt = dt_bits.astype("<u4").view("<f4").astype(np.float64)
    vel16 = None if vel is None or width == 7 else vel.astype("<f2")
    return _records(users, ns, seqs.view(np.uint64), arrivals, bases, streams, dt, poses, vel16)


def _records(
    users: NDArray[np.int64],
    ns: NDArray[np.int64],
    seqs: NDArray[np.uint64],
    arrivals: NDArray[np.float64],
    bases: NDArray[np.int64],
    streams: NDArray[np.int64],
    dt: NDArray[np.float64],
    poses: NDArray[np.float32],
    vel16: NDArray[np.float16] | None,
) -> list[PoseRecord]:
    """Decoded columns, update by update, as layout 1 records."""
    out = []
    at = 0
    for i, n in enumerate(ns.tolist()):
        base = int(bases[i]) / 1e6
        sl = slice(at, at + n)
        at += n
        p = poses[sl]
        p.flags.writeable = False
        out.append(
            PoseRecord(
                int(users[i]),
                int(seqs[i]),
                float(arrivals[i]),
                streams[sl].astype(np.uint16),
                dt[sl] + base,
                p,
                None if vel16 is None else vel16[sl],
            )
        )
    return out


def is_group(data: bytes | bytearray | memoryview) -> bool:
    """True if a ``poses`` message is in layout 2 (its first byte is the version)."""
    return len(data) > 0 and data[0] == COMPACT_VERSION


def expand_group(data: bytes | bytearray | memoryview) -> list[tuple[int, int, bytes]]:
    """The layout 1 messages of a layout 2 message's updates: (log ns, publish ns, data).

    What the recorder would have written for each update in layout 1 (log
    time: its arrival; publish time: its newest capture), so that every reader
    of layout 1 reads layout 2 files unchanged. Raises :class:`FormatError`.
    """
    out = []
    for r in decode_group(data):
        caps = r.capture_times
        newest = to_ns(float(caps.max())) if len(caps) else to_ns(r.arrival)
        raw = encode_pose(r.user, r.seq, r.arrival, r.streams, caps, r.poses, r.velocities)
        out.append((to_ns(r.arrival), newest, raw))
    return out
