"""Reading the relay's group snapshots (``protocol.codec_relay`` writes them, and its
docstring states the layout): the format's constants, the delta check, the decoder
and the header counter a meter uses without decoding.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from posecast.protocol.bits import (
    IntReader,
    unzz,
)
from posecast.protocol.codec_frame import (
    F_VELOCITY,
    BaselineMismatch,
    HeaderRules,
    _read_header,
    _read_uvarint,
)
from posecast.protocol.codec_quant import (
    ROTATION_BITS,
    M,
    Volume,
    codes_problem_rows,
    dequantise,
    remote_error,
)
from posecast.protocol.codec_small import predict_row
from posecast.protocol.errors import ErrorCode

__all__ = [
    "RELAY_CODEC_VERSION",
    "RelayEntry",
    "RelaySnapshot",
    "baseline_check",
    "decode_relay_snapshot",
    "snapshot_counts",
]

RELAY_CODEC_VERSION = 2
_F_SPLIT = 4
_TIME_MS_LIMIT = 1 << 30
#: Version 2 (snapshots only: no update flag) knows velocity and split, bounds the
#: counts after the nibbles only, and refuses a frame without an entry.
RELAY_RULES = HeaderRules(RELAY_CODEC_VERSION, F_VELOCITY | _F_SPLIT, False, True)
_ID_MAX = 0xFFFF

Row = list[int]
#: (user, stream, capture time, codes, baseline codes or None for a key entry)
RelayEntry = tuple[int, int, float, Row, Row | None]


_CHECKS = {7: struct.Struct("<HH7i"), 13: struct.Struct("<HH13i")}


def baseline_check(user: int, stream: int, baseline: Row) -> int:
    """One delta entry's share of the frame check (XORed over the entries): the CRC-32
    of (user u16, stream u16, baseline codes int32...) little-endian."""
    return zlib.crc32(_CHECKS[len(baseline)].pack(user, stream, *baseline))


@dataclass(frozen=True, slots=True)
class RelaySnapshot:
    """A decoded relay snapshot, entries in (user, stream) order (key and delta mixed)."""

    tick: int
    base_time: float
    users: list[int]
    streams: list[int]
    capture_times: list[float]
    codes: list[Row]
    volume: Volume

    def __len__(self) -> int:
        return len(self.codes)

    def arrays(self) -> tuple[NDArray[np.float32], NDArray[np.float32] | None]:
        """Poses (n, 7) float32 and velocities (n, 6) or None: ``dequantise(codes)``."""
        width = len(self.codes[0]) if self.codes else 7
        codes = np.array(self.codes, np.int64).reshape(len(self.codes), width)
        return dequantise(codes, self.volume)

    def remember(self, baselines: dict[tuple[int, int], Row]) -> None:
        """Store each entry's codes as its stream's baseline."""
        for u, s, row in zip(self.users, self.streams, self.codes, strict=True):
            baselines[(u, s)] = row


def _read_section(
    r: IntReader,
    n: int,
    nib: list[int],
    delta: bool,
    width: int,
    volume: Volume,
    baselines: Mapping[tuple[int, int], Row],
    out: tuple[list[int], list[int], list[int], list[Row]],
) -> int:
    """Read one section's entries into ``out``; the XOR of the delta checks."""
    users, streams, offs, rows = out
    kt = nib[0]
    bx, by, bz = volume.bits
    user = stream = off = 0
    check = 0
    for i in range(n):
        gap = r.eg(0)
        new = i == 0 or gap > 0
        user += gap
        sg = r.eg(0)
        stream = sg if new else stream + sg + 1
        off = unzz(r.eg(kt)) if new else off + unzz(r.eg(0))
        if user > _ID_MAX or stream > _ID_MAX or abs(off) >= _TIME_MS_LIMIT:
            raise remote_error(ErrorCode.BAD_MESSAGE, "id or time out of range in pose frame")
        if not delta:
            v = r.field(2 + 3 * ROTATION_BITS + bx + by + bz)
            pz, v = v & ((1 << bz) - 1), v >> bz
            py, v = v & ((1 << by) - 1), v >> by
            px, v = v & ((1 << bx) - 1), v >> bx
            c, v = (v & 0x1FFF) - M, v >> 13
            b, v = (v & 0x1FFF) - M, v >> 13
            a, idx = (v & 0x1FFF) - M, v >> 13
            row = [idx, a, b, c, px, py, pz]
            if width == 13:
                row += [unzz(r.eg(nib[1] if j < 3 else nib[2])) for j in range(6)]
        else:
            base = baselines.get((user, stream))
            if base is None or len(base) != width:
                raise BaselineMismatch(
                    f"delta for stream {stream} of user {user} without a baseline"
                )
            base = base.tolist() if isinstance(base, np.ndarray) else list(base)
            check ^= baseline_check(user, stream, base)
            idx = (base[0] + r.eg(0)) & 3
            cls = 0 if new else 1
            p = predict_row(base, idx)
            k = nib[1 + cls]
            row = [idx] + [p[j] + unzz(r.eg(k)) for j in range(3)]
            k = nib[3 + cls]
            row += [base[c] + unzz(r.eg(k)) for c in range(4, 7)]
            if width == 13:
                for lo, at in ((7, 5), (10, 7)):
                    k = nib[at + cls]
                    row += [base[c] + unzz(r.eg(k)) for c in range(lo, lo + 3)]
        users.append(user)
        streams.append(stream)
        offs.append(off)
        rows.append(row)
    return check


def snapshot_counts(data: bytes) -> tuple[int, int, int, int]:
    """(tick, base time us, n_key, n_delta) from a relay snapshot's header alone, for
    a meter that counts frames without decoding them; raises ``RemoteProtocolError``."""
    tick, pos = _read_uvarint(data, 2)
    z, pos = _read_uvarint(data, pos)
    nk, pos = _read_uvarint(data, pos)
    nd, _ = _read_uvarint(data, pos)
    return tick, unzz(z), nk, nd


def decode_relay_snapshot(
    data: bytes, volume: Volume, baselines: Mapping[tuple[int, int], Row] | None = None
) -> RelaySnapshot:
    """Decode a relay snapshot; raises only ``RemoteProtocolError`` (with a code).

    Baselines are code rows keyed by (user, stream) (lists or int arrays); a delta
    entry without one, or a check that differs from the baselines held, raises
    :class:`BaselineMismatch` and nothing of the frame is shown.
    """
    data = bytes(data)
    h = _read_header(data, False, volume, RELAY_RULES)
    nk, nd, nib, width = h.n_key, h.n_delta, h.nibbles, h.width
    knib_n = (1 + (2 if h.velocity else 0)) if nk else 0
    r = IntReader(data[h.size :])
    out: tuple[list[int], list[int], list[int], list[Row]] = ([], [], [], [])
    held = baselines or {}
    if nk:
        _read_section(r, nk, nib[:knib_n], False, width, volume, held, out)
    if nd:
        got = _read_section(r, nd, nib[knib_n:], True, width, volume, held, out)
        if got != h.check:
            raise BaselineMismatch("delta frame coded against other baselines (check differs)")
    r.finish()
    users, streams, offs, rows = out
    problem = codes_problem_rows(rows, volume)
    if problem:
        raise remote_error(ErrorCode.BAD_MESSAGE, f"pose frame decodes out of range: {problem}")
    order = sorted(range(len(rows)), key=lambda i: (users[i], streams[i]))
    if len({(users[i], streams[i]) for i in order}) != len(order):
        raise remote_error(ErrorCode.BAD_MESSAGE, "a stream twice in one pose frame")
    base = h.base_us / 1e6
    return RelaySnapshot(
        h.number,
        base,
        [users[i] for i in order],
        [streams[i] for i in order],
        [base - offs[i] / 1000.0 for i in order],
        [rows[i] for i in order],
        volume,
    )
