"""Frame layout of the compact pose codec: header, sections and columns, both ways.

``protocol.codec``'s module docstring specifies the layout; this module writes and
reads it (quantisation is in ``protocol.codec_quant``, bit packing in
``protocol.bits``). :func:`encode_frame` takes validated inputs; :func:`decode_frame`
takes untrusted bytes and raises only ``RemoteProtocolError`` (with a code).
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Iterator, Mapping, MutableMapping
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from posecast.protocol.bits import BitReader, BitWriter, best_k, unzz, zz
from posecast.protocol.codec_quant import (
    ROTATION_BITS,
    M,
    Volume,
    codes_problem,
    dequantise,
    local_error,
    predict_rotation,
    remote_error,
)
from posecast.protocol.errors import ErrorCode, RemoteProtocolError

__all__ = [
    "CODEC_MAGIC",
    "CODEC_VERSION",
    "F_UPDATE",
    "F_VELOCITY",
    "BaselineMismatch",
    "Encoded",
    "PoseFrame",
    "decode_frame",
    "encode_frame",
]

I64 = NDArray[np.int64]
Bools = NDArray[np.bool_]

CODEC_MAGIC = 0xC1
CODEC_VERSION = 1
F_UPDATE = 1
F_VELOCITY = 2
_F_SPLIT = 4
_FLAGS_KNOWN = 7
_TIME_MS_LIMIT = 1 << 30
_US_LIMIT = 1 << 62
_MAX_VARINT_BYTES = 10
_ID_MAX = 0xFFFF


class BaselineMismatch(RemoteProtocolError):
    """A delta frame names a stream the decoder has no baseline for, or other baselines.

    Code ``bad-baseline`` (fatal): the receiver cannot show that frame; the sender
    must start again from a key frame.
    """

    def __init__(self, message: str) -> None:
        super().__init__(ErrorCode.BAD_BASELINE, message)


@dataclass(frozen=True, slots=True, eq=False)
class PoseFrame:
    """A decoded (or just encoded) codec frame, entries sorted by (user, stream)."""

    kind: Literal["snapshot", "update"]
    number: int
    """Tick (snapshot) or sequence number (update)."""
    base_time: float
    """Server time the capture offsets count back from (whole microseconds)."""
    users: I64
    """User ids (n,), zeros in an update."""
    streams: I64
    capture_times: NDArray[np.float64]
    codes: I64
    """Quantised values (n, 7 or 13): exactly what the encoder quantised."""
    delta: Bools
    """Which entries were delta-coded."""
    volume: Volume

    def __len__(self) -> int:
        return int(self.codes.shape[0])

    @property
    def poses(self) -> NDArray[np.float32]:
        """Poses (n, 7) float32, ``dequantise(codes)``."""
        return dequantise(self.codes, self.volume)[0]

    @property
    def velocities(self) -> NDArray[np.float32] | None:
        """Velocities (n, 6) float32, or None without the velocity variant."""
        return dequantise(self.codes, self.volume)[1]

    def remember(self, baselines: MutableMapping[Any, I64]) -> None:
        """Store each entry's codes as its stream's baseline (both ends call this)."""
        if self.kind == "update":
            for s, row in zip(self.streams.tolist(), self.codes, strict=True):
                baselines[s] = row
        else:
            for u, s, row in zip(
                self.users.tolist(), self.streams.tolist(), self.codes, strict=True
            ):
                baselines[(u, s)] = row


@dataclass(frozen=True, slots=True)
class Encoded:
    """An encoded frame and what it holds (``frame.remember`` updates baselines)."""

    data: bytes
    frame: PoseFrame
    entry_bits: I64
    """Bits of the bitstream each entry (in ``frame`` order) cost; the header and the
    padding (``len(data) - entry_bits.sum() / 8`` bytes) are shared by all."""


# --------------------------------------------------------------------------- shared


def _uvarint(value: int) -> bytes:
    out = bytearray()
    while value >= 0x80:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def _svarint(value: int) -> bytes:
    return _uvarint(zz(value))


def _read_uvarint(data: bytes, pos: int) -> tuple[int, int]:
    value = 0
    for i in range(_MAX_VARINT_BYTES):
        if pos + i >= len(data):
            raise remote_error(ErrorCode.BAD_FRAME, "pose frame header truncated")
        byte = data[pos + i]
        value |= (byte & 0x7F) << (7 * i)
        if byte < 0x80:
            return value, pos + i + 1
    raise remote_error(ErrorCode.BAD_FRAME, "varint too long in pose frame header")


def _classes(streams: I64, split: bool) -> I64:
    if not split:
        return np.zeros(streams.size, np.int64)
    out: I64 = (streams != 0).astype(np.int64)
    return out


def _baseline_rows(keys: list[Any], baselines: Mapping[Any, I64], width: int) -> I64:
    rows = []
    for key in keys:
        row = baselines.get(key)
        if row is None:
            raise BaselineMismatch(f"delta for stream {key} without a baseline")
        row = np.asarray(row)
        if row.shape != (width,) or row.dtype.kind not in "iu":
            raise BaselineMismatch(f"baseline of stream {key} has another layout")
        rows.append(row)
    return np.array(rows, np.int64).reshape(len(keys), width)


def _check_size(update: bool) -> int:
    # Snapshots (what a viewer shows): the whole CRC-32. Updates (3 poses, where
    # 2 bytes are 0.7 B a pose): its low 16 bits.
    return 2 if update else 4


def _check(rows: I64, update: bool) -> int:
    """The CRC of the baselines' codes, cut to the frame kind's check size."""
    return zlib.crc32(rows.astype("<i4").tobytes()) & ((1 << (8 * _check_size(update))) - 1)


def _names(users: I64, streams: I64, update: bool) -> list[Any]:
    """Baseline keys: stream ids in an update, (user, stream) pairs in a snapshot."""
    if update:
        return list(streams.tolist())
    return list(zip(users.tolist(), streams.tolist(), strict=True))


# --------------------------------------------------------------------------- encoding


def _id_columns(users: I64, streams: I64) -> tuple[I64, I64, Bools]:
    n = users.size
    ug = np.diff(users, prepend=0)
    new = ug > 0
    if n:
        new[0] = True
    prev = np.concatenate([[-1], streams[:-1]])
    sg = np.where(new, streams, streams - prev - 1)
    return ug, sg, new


def _write_time(w: BitWriter, off: I64, new: Bools, own: I64) -> int:
    first = zz(off[new])
    k, _ = best_k(first)
    w.exp_golomb(first, k, own[new])
    same = zz(np.diff(off, prepend=0)[~new])
    w.exp_golomb(same, 0, own[~new])
    return k


def _write_classed(w: BitWriter, values: I64, cls: I64, own: I64) -> list[int]:
    ks = []
    z = zz(values)
    for c in (0, 1):
        k, _ = best_k(z[cls == c].reshape(-1))
        ks.append(k)
    for j in range(values.shape[1]):
        for c in (0, 1):
            m = cls == c
            w.exp_golomb(z[m, j], ks[c], own[m])
    return ks


def _base_us(number: int, base_time: float, capture_times: NDArray[np.float64]) -> int:
    """Check the frame number and base time; the base time in whole microseconds."""
    if type(number) is not int or not 0 <= number < (1 << 63):
        raise local_error(ErrorCode.BAD_MESSAGE, "tick/seq must be an int in [0, 2**63)")
    if not math.isfinite(base_time) or abs(base_time) * 1e6 >= _US_LIMIT:
        raise local_error(ErrorCode.BAD_MESSAGE, "base time must be finite and within range")
    if not np.isfinite(capture_times).all():
        raise local_error(ErrorCode.BAD_POSE, "non-finite capture time")
    return round(base_time * 1e6)


@dataclass(frozen=True, slots=True)
class _Entries:
    """The entries of a frame to encode, sorted by (user, stream)."""

    users: I64
    streams: I64
    off_ms: I64
    codes: I64


def _sorted_entries(
    users: I64, streams: I64, capture_times: NDArray[np.float64], codes: I64, base: float
) -> _Entries:
    off = np.rint((base - capture_times) * 1000.0)
    if codes.shape[0] and float(np.abs(off).max()) >= _TIME_MS_LIMIT:
        raise local_error(ErrorCode.BAD_POSE, "capture time too far from the base time")
    off_ms = off.astype(np.int64)
    key = (users << 16) | streams
    order = np.argsort(key, kind="stable")
    if codes.shape[0] and bool((np.diff(key[order]) == 0).any()):
        raise local_error(ErrorCode.DUPLICATE_STREAM, "a stream appears twice in one frame")
    return _Entries(users[order], streams[order], off_ms[order], codes[order])


def _write_ids_and_times(w: BitWriter, e: _Entries, sel: I64, update: bool) -> int:
    """The ug, sg, t_first and t_same columns of a section; the t_first order k."""
    ug, sg, new = _id_columns(e.users[sel], e.streams[sel])
    if not update:
        w.exp_golomb(ug, 0, sel)
    w.exp_golomb(sg, 0, sel)
    return _write_time(w, e.off_ms[sel], new, sel)


def _write_key_section(
    w: BitWriter, e: _Entries, sel: I64, update: bool, volume: Volume
) -> list[int]:
    nibbles = [_write_ids_and_times(w, e, sel, update)]
    c = e.codes[sel]
    w.fixed(c[:, 0], 2, sel)
    for j in (1, 2, 3):
        w.fixed(c[:, j] + M, ROTATION_BITS, sel)
    for j, bits in zip((4, 5, 6), volume.bits, strict=True):
        w.fixed(c[:, j], bits, sel)
    if c.shape[1] == 13:
        for cols in ((7, 8, 9), (10, 11, 12)):
            z = zz(c[:, cols])
            k, _ = best_k(z.reshape(-1))
            nibbles.append(k)
            for j in range(3):
                w.exp_golomb(z[:, j], k, sel)
    return nibbles


def _write_delta_section(
    w: BitWriter,
    e: _Entries,
    sel: I64,
    names: list[Any],
    baselines: Mapping[Any, I64],
    update: bool,
    split: bool,
) -> tuple[bytes, list[int]]:
    """Write the delta section; the baselines' check bytes and the section's orders."""
    c = e.codes[sel]
    try:
        base_rows = _baseline_rows([names[i] for i in sel], baselines, c.shape[1])
    except BaselineMismatch as exc:
        raise local_error(ErrorCode.BAD_MESSAGE, exc.message) from None
    check = _check(base_rows, update).to_bytes(_check_size(update), "little")
    nibbles = [_write_ids_and_times(w, e, sel, update)]
    cls = _classes(e.streams[sel], split)
    w.exp_golomb((c[:, 0] - base_rows[:, 0]) & 3, 0, sel)
    pred = predict_rotation(base_rows, c[:, 0])
    nibbles += _write_classed(w, c[:, 1:4] - pred, cls, sel)
    for lo in range(4, c.shape[1], 3):
        nibbles += _write_classed(w, c[:, lo : lo + 3] - base_rows[:, lo : lo + 3], cls, sel)
    return check, nibbles


def encode_frame(
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
) -> Encoded:
    """Encode validated entries (ids in range, codes valid) as one frame."""
    base_us = _base_us(number, base_time, capture_times)
    base = base_us / 1e6
    update = bool(flags & F_UPDATE)
    if split:
        flags |= _F_SPLIT
    e = _sorted_entries(users, streams, capture_times, codes, base)
    n = codes.shape[0]
    names = _names(e.users, e.streams, update)
    if baselines:
        is_delta = np.array([name in baselines for name in names], bool).reshape(n)
    else:
        is_delta = np.zeros(n, bool)
    kd = np.flatnonzero(~is_delta)
    dd = np.flatnonzero(is_delta)
    w = BitWriter()
    nibbles: list[int] = []
    check = b""
    if kd.size:
        nibbles += _write_key_section(w, e, kd, update, volume)
    if dd.size:
        check, more = _write_delta_section(w, e, dd, names, baselines or {}, update, split)
        nibbles += more
    if len(nibbles) % 2:
        nibbles.append(0)
    header = (
        bytes([CODEC_MAGIC, flags | (CODEC_VERSION << 4)])
        + _uvarint(number)
        + _svarint(base_us)
        + _uvarint(kd.size)
        + _uvarint(dd.size)
        + check
        + bytes((a << 4) | b for a, b in zip(nibbles[::2], nibbles[1::2], strict=True))
    )
    kind: Literal["snapshot", "update"] = "update" if update else "snapshot"
    times = base - e.off_ms / 1000.0
    frame = PoseFrame(kind, number, base, e.users, e.streams, times, e.codes, is_delta, volume)
    return Encoded(header + w.getvalue(), frame, w.bits_per_owner(n))


# --------------------------------------------------------------------------- decoding


@dataclass(frozen=True, slots=True)
class _Header:
    number: int
    base_us: int
    update: bool
    velocity: bool
    split: bool
    n_key: int
    n_delta: int
    check: int | None
    nibbles: list[int]
    size: int
    """Bytes of the header (the bitstream starts there)."""

    @property
    def width(self) -> int:
        return 13 if self.velocity else 7


@dataclass(frozen=True, slots=True)
class HeaderRules:
    """What one codec version's header reader accepts (:func:`_read_header`)."""

    version: int
    """The codec version the flags byte must state (its high nibble)."""
    flags: int
    """The flag bits it knows (any other set: ``bad-frame``)."""
    entries_per_bit: bool
    """Refuse counts over one entry per bit left (``bad-frame``) as soon as they are
    read, before the check and the nibbles (version 1)."""
    entries_required: bool
    """A frame without an entry is ``bad-message`` (version 2)."""


#: Version 1: snapshots and updates of ``codec_frame`` and ``codec_fast``.
FRAME_RULES = HeaderRules(CODEC_VERSION, _FLAGS_KNOWN, True, False)


def _read_flags(data: bytes, want_update: bool, rules: HeaderRules = FRAME_RULES) -> int:
    if len(data) < 2 or data[0] != CODEC_MAGIC:
        raise remote_error(ErrorCode.BAD_FRAME, "not a codec pose frame")
    flags = data[1]
    if flags >> 4 != rules.version or flags & 0x0F & ~rules.flags:
        raise remote_error(ErrorCode.BAD_FRAME, "unknown codec version or flags")
    if bool(flags & F_UPDATE) != want_update:
        raise remote_error(
            ErrorCode.BAD_MESSAGE, "an update where a snapshot was expected, or back"
        )
    return flags


def _read_nibbles(data: bytes, pos: int, n_nib: int) -> tuple[list[int], int]:
    n_bytes = (n_nib + 1) // 2
    if pos + n_bytes > len(data):
        raise remote_error(ErrorCode.BAD_FRAME, "pose frame header truncated")
    nib: list[int] = []
    for byte in data[pos : pos + n_bytes]:
        nib += [byte >> 4, byte & 0x0F]
    if len(nib) > n_nib and nib[-1]:
        raise remote_error(ErrorCode.BAD_FRAME, "non-zero padding nibble")
    return nib[:n_nib], pos + n_bytes


def _min_entry_bits(update: bool, velocity: bool, volume: Volume) -> tuple[int, int]:
    """Fewest bits a key entry and a delta entry can take in the bitstream.

    ug (snapshots) + sg + time: one bit each at least; key: idx 2 + 3 x 13 +
    the position bits; delta: idx and 6 differences, one bit each; velocities:
    6 codes of one bit at least.
    """
    common = (0 if update else 1) + 2 + (6 if velocity else 0)
    return common + 2 + 3 * ROTATION_BITS + sum(volume.bits), common + 7


def _read_header(
    data: bytes, want_update: bool, volume: Volume, rules: HeaderRules = FRAME_RULES
) -> _Header:
    """The header of a codec frame (both versions: ``rules`` says which); raises
    ``RemoteProtocolError`` (with a code) for a header that is not one."""
    flags = _read_flags(data, want_update, rules)
    update = bool(flags & F_UPDATE)
    velocity = bool(flags & F_VELOCITY)
    number, pos = _read_uvarint(data, 2)
    if number >= 1 << 63:
        raise remote_error(ErrorCode.BAD_MESSAGE, f"{'seq' if update else 'tick'} over 2**63")
    z, pos = _read_uvarint(data, pos)
    base_us = unzz(z)
    if abs(base_us) >= _US_LIMIT:
        raise remote_error(ErrorCode.BAD_MESSAGE, "base time out of range")
    nk, pos = _read_uvarint(data, pos)
    nd, pos = _read_uvarint(data, pos)
    if rules.entries_required and nk + nd == 0:
        raise remote_error(ErrorCode.BAD_MESSAGE, "empty pose frame")
    # Every entry costs at least one bit (its stream code): bound n by the frame.
    if rules.entries_per_bit and nk + nd > 8 * (len(data) - pos):
        raise remote_error(ErrorCode.BAD_FRAME, "more entries than the frame can hold")
    check = None
    if nd:
        size = _check_size(update)
        if pos + size > len(data):
            raise remote_error(ErrorCode.BAD_FRAME, "pose frame header truncated")
        check = int.from_bytes(data[pos : pos + size], "little")
        pos += size
    n_nib = (1 + (2 if velocity else 0) if nk else 0) + (5 + (4 if velocity else 0) if nd else 0)
    nibbles, pos = _read_nibbles(data, pos, n_nib)
    # Refuse counts the bitstream cannot hold before allocating anything for them.
    key_bits, delta_bits = _min_entry_bits(update, velocity, volume)
    if nk * key_bits + nd * delta_bits > 8 * (len(data) - pos):
        raise remote_error(ErrorCode.BAD_FRAME, "more entries than the frame can hold")
    split = bool(flags & _F_SPLIT)
    return _Header(number, base_us, update, velocity, split, nk, nd, check, nibbles, pos)


def _absmax(values: I64) -> int:
    return int(np.abs(values).max()) if values.size else 0


def _read_time(r: BitReader, k: int, new: Bools) -> I64:
    n = new.size
    first = unzz(r.exp_golomb(int(new.sum()), k))
    same = unzz(r.exp_golomb(n - int(new.sum()), 0))
    if max(_absmax(first), _absmax(same)) >= _TIME_MS_LIMIT:
        raise remote_error(ErrorCode.BAD_POSE, "capture time too far from the base time")
    steps = np.empty(n, np.int64)
    steps[new] = first
    steps[~new] = same
    # offset = first of the user's run + the steps since; new entries restart the sum.
    runs = np.cumsum(new) - 1
    cs = np.cumsum(np.where(new, 0, steps))
    starts = np.flatnonzero(new)
    offsets: I64 = first[runs] + cs - cs[starts][runs]
    if _absmax(offsets) >= _TIME_MS_LIMIT:
        raise remote_error(ErrorCode.BAD_POSE, "capture time too far from the base time")
    return offsets


def _read_ids(r: BitReader, n: int, update: bool) -> tuple[I64, I64, Bools]:
    ug = np.zeros(n, np.int64) if update else r.exp_golomb(n, 0)
    sg = r.exp_golomb(n, 0)
    if int(ug.max()) > _ID_MAX or int(sg.max()) > _ID_MAX:
        raise remote_error(ErrorCode.BAD_MESSAGE, "user or stream id over 65535 in a pose frame")
    users = np.cumsum(ug)
    new = ug > 0
    new[0] = True
    inc = sg + 1
    runs = np.cumsum(new) - 1
    cs = np.cumsum(inc)
    starts = np.flatnonzero(new)
    streams = cs - (cs[starts] - inc[starts])[runs] - 1
    if int(users[-1]) > _ID_MAX or int(streams.max()) > _ID_MAX:
        raise remote_error(ErrorCode.BAD_MESSAGE, "user or stream id over 65535 in a pose frame")
    return users, streams, new


def _read_classed(r: BitReader, cls: I64, ks: list[int]) -> I64:
    out = np.empty((cls.size, 3), np.int64)
    for j in range(3):
        for c in (0, 1):
            m = cls == c
            out[m, j] = unzz(r.exp_golomb(int(m.sum()), ks[c]))
    return out


_Part = tuple[I64, I64, I64, I64]


def _read_key_section(r: BitReader, h: _Header, nibbles: Iterator[int], volume: Volume) -> _Part:
    n = h.n_key
    users, streams, new = _read_ids(r, n, h.update)
    off = _read_time(r, next(nibbles), new)
    codes = np.empty((n, h.width), np.int64)
    codes[:, 0] = r.fixed(n, 2)
    for j in (1, 2, 3):
        codes[:, j] = r.fixed(n, ROTATION_BITS) - M
    for j, bits in zip((4, 5, 6), volume.bits, strict=True):
        codes[:, j] = r.fixed(n, bits)
    for lo in range(7, h.width, 3):
        k = next(nibbles)
        for j in range(lo, lo + 3):
            codes[:, j] = unzz(r.exp_golomb(n, k))
    return users, streams, off, codes


def _read_delta_section(
    r: BitReader, h: _Header, nibbles: Iterator[int], baselines: Mapping[Any, I64]
) -> _Part:
    n = h.n_delta
    users, streams, new = _read_ids(r, n, h.update)
    off = _read_time(r, next(nibbles), new)
    base_rows = _baseline_rows(_names(users, streams, h.update), baselines, h.width)
    if _check(base_rows, h.update) != h.check:
        raise BaselineMismatch("baselines differ from the encoder's (CRC mismatch)")
    cls = _classes(streams, h.split)
    codes = np.empty((n, h.width), np.int64)
    codes[:, 0] = (base_rows[:, 0] + r.exp_golomb(n, 0)) & 3
    refs = [predict_rotation(base_rows, codes[:, 0])]
    refs += [base_rows[:, lo : lo + 3] for lo in range(4, h.width, 3)]
    for lo, ref in zip(range(1, h.width, 3), refs, strict=True):
        ks = [next(nibbles), next(nibbles)]
        codes[:, lo : lo + 3] = ref + _read_classed(r, cls, ks)
    return users, streams, off, codes


def _assemble(parts: list[_Part], h: _Header, volume: Volume) -> PoseFrame:
    """The frame of the decoded sections: codes checked, entries sorted, no duplicates."""
    if parts:
        users, streams, off, codes = (np.concatenate([part[i] for part in parts]) for i in range(4))
        problem = codes_problem(codes, volume)
        if problem:
            raise remote_error(ErrorCode.BAD_POSE, problem)
    else:
        codes = np.zeros((0, h.width), np.int64)
        users = streams = off = np.zeros(0, np.int64)
    is_delta = np.arange(users.size) >= h.n_key
    key = (users << 16) | streams
    order = np.argsort(key, kind="stable")
    if users.size and bool((np.diff(key[order]) == 0).any()):
        raise remote_error(ErrorCode.BAD_MESSAGE, "a stream appears twice in one pose frame")
    base = h.base_us / 1e6
    kind: Literal["snapshot", "update"] = "update" if h.update else "snapshot"
    times = base - off[order] / 1000.0
    return PoseFrame(
        kind,
        h.number,
        base,
        users[order],
        streams[order],
        times,
        codes[order],
        is_delta[order],
        volume,
    )


def decode_frame(
    data: bytes, volume: Volume, baselines: Mapping[Any, I64] | None, want_update: bool
) -> PoseFrame:
    """Decode untrusted bytes; raises only ``RemoteProtocolError`` (with a code)."""
    data = bytes(data)
    h = _read_header(data, want_update, volume)
    r = BitReader(memoryview(data)[h.size :])
    nibbles = iter(h.nibbles)
    parts: list[_Part] = []
    if h.n_key:
        parts.append(_read_key_section(r, h, nibbles, volume))
    if h.n_delta:
        parts.append(_read_delta_section(r, h, nibbles, baselines or {}))
    r.finish()
    return _assemble(parts, h, volume)
