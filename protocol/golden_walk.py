"""A second reader of compact frames, written from ``docs/protocol.md`` alone.

It decodes version-1 update frames and version-2 snapshot frames field by field
with plain Python ints (no numpy, none of ``protocol.codec*``), and records every
field it reads: where it starts (bit offset), how wide it is, what it is called
and what it holds. Two uses: the golden vectors are checked against it (so the
spec, not only the codec, is tested by every vector), and the worked examples of
``docs/protocol.md`` are printed from its records (``field_table``).
"""

from __future__ import annotations

import math
import struct
import zlib
from collections.abc import Mapping
from dataclasses import dataclass, field, replace

__all__ = [
    "Field",
    "WalkError",
    "Walked",
    "field_table",
    "predict",
    "volume_geometry",
    "walk_snapshot",
    "walk_update",
]

M = 4095
OTHERS = ((1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2))
Row = list[int]


class WalkError(Exception):
    """The frame breaks the spec; ``code`` is the error code a receiver answers with."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(f"{code}: {message}")
        self.code = code


@dataclass(frozen=True)
class Field:
    """One field of a frame: bit offset from the frame's start, width in bits."""

    at: int
    width: int
    name: str
    value: int
    in_bytes: bool = False
    """A header field of whole bytes (shown in hex)."""
    note: str = ""
    """What the value means, where it is not the value itself."""


@dataclass
class Walked:
    """A frame read by the walker: header values, entries and every field."""

    number: int
    base_us: int
    entries: list[dict[str, object]]
    fields: list[Field] = field(default_factory=list)


def volume_geometry(lo: tuple[float, ...], hi: tuple[float, ...]) -> tuple[list[int], list[float]]:
    """Bits per axis and step per axis (m) of a room volume, as the spec defines them."""
    spans = [h - a for a, h in zip(lo, hi, strict=True)]
    bits = [max(1, math.ceil(math.log2(span / 0.0005 + 1.0))) for span in spans]
    steps = [(h - a) / ((1 << b) - 1) for a, h, b in zip(lo, hi, bits, strict=True)]
    return bits, steps


def predict(base: Row, idx: int) -> Row:
    """The baseline rotation re-expressed with largest index ``idx`` (spec, integers only)."""
    i0, a, b, c = base[0], base[1], base[2], base[3]
    rest = max(0, 2 * M * M - (a * a + b * b + c * c))
    full = [0, 0, 0, 0]
    full[i0] = (math.isqrt(4 * rest) + 1) // 2
    for o, v in zip(OTHERS[i0], (a, b, c), strict=True):
        full[o] = v
    sign = -1 if full[idx] < 0 else 1
    return [min(M, max(-M, sign * full[o])) for o in OTHERS[idx]]


def _unzz(z: int) -> int:
    return (z >> 1) ^ -(z & 1)


class _Bits:
    def __init__(self, data: bytes, start: int, fields: list[Field]) -> None:
        self.data = data
        self.pos = 8 * start
        self.size = 8 * len(data)
        self.fields = fields

    def bit(self) -> int:
        if self.pos >= self.size:
            raise WalkError("bad-frame", "truncated")
        byte = self.data[self.pos >> 3]
        self.pos += 1
        return (byte >> (7 - ((self.pos - 1) & 7))) & 1

    def read(self, width: int, name: str, offset: int = 0) -> int:
        """``width`` bits, MSB first, less ``offset``."""
        at, value = self.pos, 0
        for _ in range(width):
            value = (value << 1) | self.bit()
        if width:
            note = f"{value} - {offset} = {value - offset}" if offset else ""
            self.fields.append(Field(at, width, name, value, note=note))
        return value - offset

    def prefix(self, name: str) -> int:
        """Zeros up to and including the first one; the number of zeros."""
        at, zeros = self.pos, 0
        while not self.bit():
            zeros += 1
            if zeros > 48:
                raise WalkError("bad-frame", "Exp-Golomb code too long")
        self.fields.append(Field(at, zeros + 1, name + " prefix", zeros))
        return zeros

    def suffix(self, zeros: int, k: int, name: str) -> int:
        width = zeros - 1 + k if zeros else k
        s = self.read(width, name + " suffix") if width else 0
        return (1 << (zeros - 1 + k)) + s if zeros else s

    def eg(self, k: int, name: str, signed: bool = False) -> int:
        """One whole Exp-Golomb code of order k (version 2: prefix and suffix together)."""
        at = self.pos
        n_fields = len(self.fields)
        value = self.suffix(self.prefix(name), k, name)
        del self.fields[n_fields:]
        note = f"zigzag: {_unzz(value)}" if signed else ""
        self.fields.append(Field(at, self.pos - at, f"{name} EG{k}", value, note=note))
        return value

    def eg_column(self, n: int, k: int, names: list[str], signed: bool = False) -> list[int]:
        """A version-1 column: n prefixes, then n suffixes."""
        zeros = []
        where = []
        for i in range(n):
            zeros.append(self.prefix(names[i]))
            where.append(len(self.fields) - 1)
        out = []
        for i in range(n):
            before = len(self.fields)
            value = self.suffix(zeros[i], k, names[i])
            out.append(value)
            j = len(self.fields) - 1 if len(self.fields) > before else where[i]
            note = f"EG{k} code = {value}" + (f", zigzag: {_unzz(value)}" if signed else "")
            self.fields[j] = replace(self.fields[j], note=note)
        return out

    def finish(self) -> None:
        rest = self.size - self.pos
        if 0 < rest < 8:
            self.fields.append(Field(self.pos, rest, "padding", 0))
        if rest >= 8 or any(self.bit() for _ in range(rest)):
            raise WalkError("bad-frame", "trailing bits")


def _byte_field(fields: list[Field], start: int, end: int, name: str, value: int) -> None:
    fields.append(Field(8 * start, 8 * (end - start), name, value, True))


def _uvarint(data: bytes, pos: int) -> tuple[int, int]:
    value, shift = 0, 0
    while True:
        if pos >= len(data) or shift > 63:
            raise WalkError("bad-frame", "varint truncated or too long")
        byte = data[pos]
        value |= (byte & 0x7F) << shift
        pos += 1
        shift += 7
        if byte < 0x80:
            return value, pos


def _header(data: bytes, fields: list[Field], version: int) -> tuple[int, int, int, int, int, int]:
    """flags, number field, base field (zigzag), n_key, n_delta, position after them."""
    if len(data) < 2 or data[0] != 0xC1:
        raise WalkError("bad-frame", "not a compact frame")
    flags = data[1]
    if flags >> 4 != version:
        raise WalkError("bad-frame", "unknown codec version")
    _byte_field(fields, 0, 1, "magic 0xC1", 0xC1)
    _byte_field(fields, 1, 2, "flags", flags)
    bits = [
        n for b, n in ((1, "update"), (2, "velocity"), (4, "split"), (8, "relative")) if flags & b
    ]
    fields[-1] = replace(fields[-1], note=f"version {flags >> 4}; {', '.join(bits) or 'none'}")
    return flags, *_counts(data, fields)


def _counts(data: bytes, fields: list[Field]) -> tuple[int, int, int, int, int]:
    out = []
    pos = 2
    names = ("number (LEB128)", "base time (zigzag LEB128)", "n_key (LEB128)", "n_delta (LEB128)")
    for name in names:
        value, end = _uvarint(data, pos)
        _byte_field(fields, pos, end, name, value)
        if name.startswith("base"):
            fields[-1] = replace(fields[-1], note=f"zigzag: {_unzz(value)} us")
        out.append(value)
        pos = end
    number, base, nk, nd = out
    return number, base, nk, nd, pos


_KEY_ORDERS = ("key t_first", "key vlin", "key vang")
_DELTA_ORDERS = (
    "delta t_first",
    "rot0",
    "rot1",
    "pos0",
    "pos1",
    "vlin0",
    "vlin1",
    "vang0",
    "vang1",
)


def _nibbles(
    data: bytes, pos: int, nk: int, nd: int, vel: bool, fields: list[Field]
) -> tuple[list[int], int]:
    """The order nibbles of the sections present (key, then delta)."""
    names = list(_KEY_ORDERS[: 1 + 2 * vel] if nk else ()) + list(
        _DELTA_ORDERS[: 5 + 4 * vel] if nd else ()
    )
    n = len(names)
    end = pos + (n + 1) // 2
    if end > len(data):
        raise WalkError("bad-frame", "header truncated")
    nib = [x for b in data[pos:end] for x in (b >> 4, b & 15)]
    for i in range(n):
        fields.append(Field(8 * pos + 4 * i, 4, f"order {names[i]}", nib[i]))
    if len(nib) > n:
        fields.append(Field(8 * pos + 4 * n, 4, "padding nibble", nib[-1]))
        if nib[-1]:
            raise WalkError("bad-frame", "non-zero padding nibble")
    return nib[:n], end


def _rest_codes(
    r: _Bits, n: int, names: list[str], bits: list[int], vel: bool, ks: list[int]
) -> list[Row]:
    """Version-1 key columns after the ids and times."""
    idx = [r.read(2, f"{names[i]} idx") for i in range(n)]
    cols = [idx]
    for label in "abc":
        cols.append([r.read(13, f"{names[i]} {label}+4095", M) for i in range(n)])
    for j, label in enumerate(("px", "py", "pz")):
        cols.append([r.read(bits[j], f"{names[i]} {label}") for i in range(n)])
    if vel:
        orders = (ks[0],) * 3 + (ks[1],) * 3
        for label, k in zip(("vx", "vy", "vz", "wx", "wy", "wz"), orders, strict=True):
            cols.append(
                [_unzz(v) for v in r.eg_column(n, k, [f"{x} {label}" for x in names], True)]
            )
    return [[c[i] for c in cols] for i in range(n)]


def _ids_times_v1(r: _Bits, n: int, kt: int, section: str) -> tuple[list[int], list[int]]:
    names = [f"{section}[{i}]" for i in range(n)]
    sg = r.eg_column(n, 0, [f"{x} sg" for x in names])
    streams: list[int] = []
    for i, g in enumerate(sg):
        streams.append(g if i == 0 else streams[-1] + g + 1)
    first = r.eg_column(1, kt, [f"{names[0]} t_first"], True)
    same = r.eg_column(n - 1, 0, [f"{x} t_same" for x in names[1:]], True)
    offs = [_unzz(first[0])]
    for z in same:
        offs.append(offs[-1] + _unzz(z))
    return streams, offs


def _check_ranges(rows: list[Row], bits: list[int]) -> None:
    for r in rows:
        if not 0 <= r[0] <= 3 or max(abs(x) for x in r[1:4]) > M:
            raise WalkError("bad-pose", "rotation out of range")
        if r[1] ** 2 + r[2] ** 2 + r[3] ** 2 > 2 * M * M:
            raise WalkError("bad-pose", "rotation out of range")
        if any(not 0 <= r[4 + j] < 1 << bits[j] for j in range(3)):
            raise WalkError("bad-pose", "position outside the room volume")
        if len(r) == 13 and (
            max(abs(x) for x in r[7:10]) > 32768 or max(abs(x) for x in r[10:13]) > 16384
        ):
            raise WalkError("bad-pose", "velocity out of range")


def walk_update(
    data: bytes,
    volume: tuple[tuple[float, ...], tuple[float, ...]],
    baselines: Mapping[int, Row],
    previous: tuple[int, int] | None,
) -> Walked:
    """Read a version-1 update frame (relative header against ``previous`` = (seq, base us))."""
    fields: list[Field] = []
    flags, number, zbase, nk, nd, pos = _header(data, fields, 1)
    if not flags & 1:
        raise WalkError("bad-message", "a snapshot where an update was expected")
    vel, split, rel = bool(flags & 2), bool(flags & 4), bool(flags & 8)
    base_us = _unzz(zbase)
    if rel:
        if previous is None:
            raise WalkError("bad-baseline", "relative header without a previous update")
        number, base_us = previous[0] + _unzz(number), previous[1] + base_us
        fields[2] = replace(
            fields[2],
            name="seq - previous seq (zigzag LEB128)",
            note=f"zigzag: {_unzz(fields[2].value)}: seq {number}",
        )
        fields[3] = replace(
            fields[3],
            name="base - previous base (zigzag LEB128)",
            note=f"zigzag: {_unzz(fields[3].value)} us: base {base_us} us",
        )
    check = None
    if nd:
        if pos + 2 > len(data):
            raise WalkError("bad-frame", "header truncated")
        check = data[pos] | data[pos + 1] << 8
        _byte_field(fields, pos, pos + 2, "check (CRC-32 low 16 bits, LE)", check)
        pos += 2
    nib, pos = _nibbles(data, pos, nk, nd, vel, fields)
    bits, _ = volume_geometry(*volume)
    r = _Bits(data, pos, fields)
    entries: list[dict[str, object]] = []
    if nk:
        streams, offs = _ids_times_v1(r, nk, nib[0], "key")
        rows = _rest_codes(r, nk, [f"key[{i}]" for i in range(nk)], bits, vel, nib[1:3])
        entries += [
            {"stream": s, "offset_ms": o, "delta": False, "codes": c}
            for s, o, c in zip(streams, offs, rows, strict=True)
        ]
        nib = nib[1 + 2 * vel :]
    if nd:
        entries += _delta_v1(r, nd, nib, vel, split, baselines, check)
    r.finish()
    _check_ranges([e["codes"] for e in entries], bits)  # type: ignore[misc]
    return Walked(number, base_us, entries, fields)


def _delta_v1(
    r: _Bits,
    n: int,
    nib: list[int],
    vel: bool,
    split: bool,
    baselines: Mapping[int, Row],
    check: int | None,
) -> list[dict[str, object]]:
    streams, offs = _ids_times_v1(r, n, nib[0], "delta")
    names = [f"delta[{i}]" for i in range(n)]
    base = []
    for s in streams:
        if s not in baselines:
            raise WalkError("bad-baseline", f"no baseline for stream {s}")
        base.append(list(baselines[s]))
    flat = [v for row in base for v in row]
    crc = zlib.crc32(struct.pack(f"<{len(flat)}i", *flat)) & 0xFFFF
    if crc != check:
        raise WalkError("bad-baseline", "CRC mismatch")
    steps = r.eg_column(n, 0, [f"{x} idx step" for x in names])
    idx = [(b[0] + d) & 3 for b, d in zip(base, steps, strict=True)]
    cls = [1 if split and s != 0 else 0 for s in streams]
    refs = [[predict(b, i) for b, i in zip(base, idx, strict=True)]]
    labels = [("a", "b", "c"), ("px", "py", "pz")]
    if vel:
        labels += [("vx", "vy", "vz"), ("wx", "wy", "wz")]
    for g in range(1, len(labels)):
        refs.append([b[1 + 3 * g : 4 + 3 * g] for b in base])
    rows = [[i] for i in idx]
    for g, group in enumerate(labels):
        ks = nib[1 + 2 * g : 3 + 2 * g]
        for j, label in enumerate(group):
            diff = [0] * n
            for c in (0, 1):
                sel = [i for i in range(n) if cls[i] == c]
                got = r.eg_column(len(sel), ks[c], [f"{names[i]} d{label}" for i in sel], True)
                for i, z in zip(sel, got, strict=True):
                    diff[i] = _unzz(z)
            for i in range(n):
                rows[i].append(refs[g][i][j] + diff[i])
    return [
        {"stream": s, "offset_ms": o, "delta": True, "codes": c}
        for s, o, c in zip(streams, offs, rows, strict=True)
    ]


def walk_snapshot(
    data: bytes,
    volume: tuple[tuple[float, ...], tuple[float, ...]],
    baselines: Mapping[tuple[int, int], Row],
) -> Walked:
    """Read a version-2 snapshot frame against ``baselines`` keyed (user, stream)."""
    fields: list[Field] = []
    flags, number, zbase, nk, nd, pos = _header(data, fields, 2)
    if flags & 1:
        raise WalkError("bad-message", "an update where a snapshot was expected")
    vel = bool(flags & 2)
    check = None
    if nd:
        if pos + 4 > len(data):
            raise WalkError("bad-frame", "header truncated")
        check = int.from_bytes(data[pos : pos + 4], "little")
        _byte_field(fields, pos, pos + 4, "check (XOR of CRC-32s, LE)", check)
        pos += 4
    n_key_nib = 1 + 2 * vel if nk else 0
    nib, pos = _nibbles(data, pos, nk, nd, vel, fields)
    bits, _ = volume_geometry(*volume)
    r = _Bits(data, pos, fields)
    entries = _section_v2(r, nk, nib[:n_key_nib], False, vel, bits, baselines, "key")
    crc: list[int] = []
    entries += _section_v2(r, nd, nib[n_key_nib:], True, vel, bits, baselines, "delta", crc)
    r.finish()
    if nd:
        got = 0
        for c in crc:
            got ^= c
        if got != check:
            raise WalkError("bad-baseline", "check mismatch")
    _check_ranges([e["codes"] for e in entries], bits)  # type: ignore[misc]
    return Walked(number, _unzz(zbase), entries, fields)


def _section_v2(
    r: _Bits,
    n: int,
    nib: list[int],
    delta: bool,
    vel: bool,
    bits: list[int],
    baselines: Mapping[tuple[int, int], Row],
    section: str,
    crc: list[int] | None = None,
) -> list[dict[str, object]]:
    out: list[dict[str, object]] = []
    user = stream = off = 0
    for i in range(n):
        name = f"{section}[{i}]"
        gap = r.eg(0, f"{name} ug")
        new = i == 0 or gap > 0
        user += gap
        sg = r.eg(0, f"{name} sg")
        stream = sg if new else stream + sg + 1
        if new:
            off = _unzz(r.eg(nib[0], f"{name} t_first", True))
        else:
            off += _unzz(r.eg(0, f"{name} t_same", True))
        if user > 0xFFFF or stream > 0xFFFF:
            raise WalkError("bad-message", "id over 65535")
        if not delta:
            row = [r.read(2, f"{name} idx")]
            row += [r.read(13, f"{name} {x}+4095", M) for x in "abc"]
            row += [r.read(bits[j], f"{name} {x}") for j, x in enumerate(("px", "py", "pz"))]
            if vel:
                row += [_unzz(r.eg(nib[1 + j // 3], f"{name} v{j}", True)) for j in range(6)]
        else:
            base = baselines.get((user, stream))
            if base is None:
                raise WalkError("bad-baseline", f"no baseline for ({user}, {stream})")
            base = list(base)
            assert crc is not None
            crc.append(zlib.crc32(struct.pack(f"<HH{len(base)}i", user, stream, *base)))
            cls = 0 if new else 1
            idx = (base[0] + r.eg(0, f"{name} idx step")) & 3
            p = predict(base, idx)
            row = [idx] + [
                p[j] + _unzz(r.eg(nib[1 + cls], f"{name} d{x}", True)) for j, x in enumerate("abc")
            ]
            groups = [("px", "py", "pz")] + (
                [("vx", "vy", "vz"), ("wx", "wy", "wz")] if vel else []
            )
            for g, group in enumerate(groups):
                k = nib[3 + 2 * g + cls]
                row += [
                    base[4 + 3 * g + j] + _unzz(r.eg(k, f"{name} d{x}", True))
                    for j, x in enumerate(group)
                ]
        out.append({"user": user, "stream": stream, "offset_ms": off, "delta": delta, "codes": row})
    return out


def field_table(data: bytes, fields: list[Field]) -> str:
    """A markdown table of ``fields``: bit offset, the bits (or bytes), name, value."""
    lines = ["| bit | bits | field | value | meaning |", "|---:|---|---|---:|---|"]
    whole = int.from_bytes(data, "big")
    size = 8 * len(data)
    for f in fields:
        raw = (whole >> (size - f.at - f.width)) & ((1 << f.width) - 1)
        if f.in_bytes:
            shown = raw.to_bytes(f.width // 8, "big").hex(" ")
        else:
            shown = format(raw, f"0{f.width}b")
        lines.append(f"| {f.at} | `{shown}` | {f.name} | {f.value} | {f.note} |")
    return "\n".join(lines)
