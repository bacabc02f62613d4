"""Compact upstream updates: a session's end of the codec's update frames.

A client that joined with ``codec="compact"`` sends each ``PoseUpdate`` as one
codec update frame (``protocol.codec``: first byte 0xC1, never msgpack),
quantised in the room volume of the server's welcome and delta-coded against
the codes it last sent for each stream (a stream's first pose goes as a key
entry). The server decodes it against its own copy of those baselines and hands
the relay the same ``PoseUpdate`` a raw client sends: the dequantised poses as
float32, capture times to the codec's millisecond.

Both ends store a frame's codes as baselines (``PoseFrame.remember``) once it
is surely sent, or decoded: the websocket is reliable and ordered, so the two
copies stay equal; a frame coded against other baselines (a CRC mismatch) or
naming a stream without one raises ``BaselineMismatch`` (fatal, ``bad-baseline``).

Relative header: every update after the first sets flag bit 3 (``F_RELATIVE``)
and carries its sequence number and base time as differences from the previous
update's (zigzag varints: usually 1 and ~33,000 us, 1 + 3 bytes instead of 2-3 +
5-8); the decoder puts the absolute values back before decoding. The frame
layout is otherwise that of ``protocol.codec`` exactly.
"""

from __future__ import annotations

import struct

import numpy as np
from numpy.typing import NDArray

from posecast.protocol import _accel
from posecast.protocol.bits import unzz, zz
from posecast.protocol.codec import (
    BaselineMismatch,
    PoseFrame,
    Volume,
    decode_update,
    encode_update_codes,
    quantise,
)
from posecast.protocol.codec_fast import UpdateGeometry, decode_update_rows, read_varint
from posecast.protocol.codec_frame import F_UPDATE, F_VELOCITY, _read_uvarint, _svarint, _uvarint
from posecast.protocol.codec_quant import dequantise_row, velocity_row
from posecast.protocol.codec_relay import decode_relay_snapshot
from posecast.protocol.errors import ProtocolViolation, RemoteProtocolError
from posecast.protocol.poses import UPDATE_DTYPE, UPDATE_VELOCITY_DTYPE, PoseUpdate, Snapshot

__all__ = ["CODEC_FRAME_BYTE", "SnapshotDecoder", "UpstreamDecoder", "UpstreamEncoder"]

#: First byte of every codec frame (the one byte msgpack never uses).
CODEC_FRAME_BYTE = 0xC1
#: Flag bit of an update whose number and base time are differences (see above).
F_RELATIVE = 8


def _header_fields(data: bytes) -> tuple[int, int, int]:
    """(number, zigzagged base time, offset of what follows) of a codec frame."""
    number, pos = _read_uvarint(data, 2)
    z, pos = _read_uvarint(data, pos)
    return number, z, pos


def relative(data: bytes, previous: tuple[int, int] | None) -> tuple[bytes, tuple[int, int]]:
    """``data`` (an absolute frame) with a relative header against ``previous``
    (number, base us), and its own (number, base us)."""
    number, z, pos = _header_fields(data)
    here = (number, unzz(z))
    if previous is None:
        return data, here
    head = bytes([data[0], data[1] | F_RELATIVE])
    fields = _uvarint(zz(number - previous[0])) + _svarint(here[1] - previous[1])
    return head + fields + data[pos:], here


def absolute(data: bytes, previous: tuple[int, int] | None) -> tuple[bytes, tuple[int, int]]:
    """The absolute frame of ``data`` (relative or not), and its (number, base us);
    raises ``RemoteProtocolError``."""
    d, z, pos = _header_fields(data)
    if not data[1] & F_RELATIVE:
        return data, (d, unzz(z))
    if previous is None:
        raise BaselineMismatch("a relative update header with no update before it")
    number = previous[0] + unzz(d)
    base = previous[1] + unzz(z)
    if not (0 <= number < 1 << 63 and abs(base) < 1 << 62):
        raise BaselineMismatch("relative update header out of range")
    head = bytes([data[0], data[1] & ~F_RELATIVE])
    return head + _uvarint(number) + _svarint(base) + data[pos:], (number, base)


Baselines = dict[int, NDArray[np.int64]]


class UpstreamEncoder:
    """The client's half: ``PoseUpdate`` -> codec update frame, baselines per stream."""

    def __init__(self, volume: Volume) -> None:
        self.volume = volume
        self.baselines: Baselines = {}
        self._pending: PoseFrame | None = None
        #: (number, base us) of the last frame sent, and of the one pending.
        self._previous: tuple[int, int] | None = None
        self._pending_header: tuple[int, int] | None = None

    def encode(self, update: PoseUpdate) -> bytes:
        """The frame of ``update``; raises ``LocalProtocolError`` (``bad-pose`` outside the
        volume). Call :meth:`commit` once the frame is surely sent."""
        velocities = update.velocities
        codes = quantise(update.poses, self.volume, velocities)
        encoded = encode_update_codes(
            update.seq,
            update.base_time,
            update.streams,
            update.capture_times,
            codes,
            self.volume,
            self.baselines,
        )
        self._pending = encoded.frame
        data, self._pending_header = relative(encoded.data, self._previous)
        return data

    def commit(self) -> None:
        """The last encoded frame was sent: its codes are the streams' new baselines."""
        if self._pending is not None:
            self._pending.remember(self.baselines)
            self._pending = None
            self._previous = self._pending_header


class UpstreamDecoder:
    """The server's half: codec update frame -> ``PoseUpdate``, baselines per stream.

    A small valid frame (the relay's every update) is read by
    ``codec_fast.decode_update_rows`` straight into code rows, and its
    ``PoseUpdate`` records are packed from them with no numpy call but the one
    that wraps the bytes (:meth:`_decode_fast`; with the compiled accelerator,
    all of it in one call, ``_speedups.decode_update``); anything else takes the
    reference path (``codec.decode_update``), which decodes it the same or raises
    its error.
    """

    def __init__(self, volume: Volume) -> None:
        self.volume = volume
        #: Stream id -> codes (Python ints) of its last decoded pose. Only decoded
        #: (hence validated) rows go in: the fast path does not check them again.
        self.baselines: dict[int, list[int]] = {}
        self._previous: tuple[int, int] | None = None
        #: Stream id -> codes of the last decoded frame: a relay forwards these codes
        #: to compact subscribers rather than quantising the decoded floats again.
        self.last_codes: dict[int, list[int]] = {}
        self._geometry = UpdateGeometry(volume)
        self._scale = (volume.lo, volume.step)

    def decode(self, data: bytes | bytearray | memoryview) -> PoseUpdate:
        """The update in ``data``; raises ``RemoteProtocolError`` (in reply to "update")."""
        data = bytes(data)
        accel = _accel.speedups
        if accel is not None:
            got = accel.decode_update(
                data, self._previous, self._geometry.packed, self.baselines, *self._scale
            )
            if got is not None:
                number, base_us, records, self.last_codes = got
                self._previous = (number, base_us)
                dtype = UPDATE_VELOCITY_DTYPE if data[1] & F_VELOCITY else UPDATE_DTYPE
                return PoseUpdate._trusted(number, base_us / 1e6, np.frombuffer(records, dtype))
        else:
            fast = self._decode_fast(data)
            if fast is not None:
                return fast
        try:
            whole, header = absolute(data, self._previous)
            frame = decode_update(whole, self.volume, self.baselines)  # type: ignore[arg-type]
        except ProtocolViolation as exc:
            raise RemoteProtocolError(exc.code, exc.message, in_reply_to="update") from None
        self._previous = header
        # The sender stored these codes when it sent them, whatever the session
        # rules say of the update next: keep the two copies equal.
        codes = frame.codes.tolist()
        self.last_codes = dict(zip(frame.streams.tolist(), codes, strict=True))
        self.baselines.update(self.last_codes)
        return PoseUpdate.from_arrays(
            frame.number,
            frame.streams,
            frame.capture_times,
            frame.poses,
            base_time=frame.base_time,
            velocities=frame.velocities,
        )

    def _decode_fast(self, data: bytes) -> PoseUpdate | None:
        """The update of a small valid frame, or None (the reference path decides)."""
        if len(data) < 4 or data[0] != CODEC_FRAME_BYTE:
            return None
        flags = data[1]
        if flags & 0xF0 != 0x10 or flags & 0x0F & ~_UPDATE_FLAGS or not flags & F_UPDATE:
            return None
        try:
            d, pos = read_varint(data, 2)
            z, pos = read_varint(data, pos)
        except (RemoteProtocolError, IndexError):
            return None
        if flags & F_RELATIVE:
            if self._previous is None:
                return None
            number = self._previous[0] + unzz(d)
            base_us = self._previous[1] + unzz(z)
        else:
            number, base_us = d, unzz(z)
        if not (0 <= number < 1 << 63 and abs(base_us) < 1 << 62):
            return None
        got = decode_update_rows(data, pos, flags, self._geometry, self.baselines)
        if got is None:
            return None
        streams, off, rows = got
        self._previous = (number, base_us)
        self.last_codes = codes = dict(zip(streams, rows, strict=True))
        self.baselines.update(codes)
        return _update_of_rows(number, base_us, streams, off, rows, self.volume)


#: Flag bits an update frame may carry: update, velocities, class split, relative.
_UPDATE_FLAGS = F_UPDATE | F_VELOCITY | 4 | F_RELATIVE
_RECORD = struct.Struct("<Hf7f")
_VELOCITY_RECORD = struct.Struct("<Hf7f6e")


def _update_of_rows(
    number: int,
    base_us: int,
    streams: list[int],
    off: list[int],
    rows: list[list[int]],
    volume: Volume,
) -> PoseUpdate:
    """The ``PoseUpdate`` that ``PoseUpdate.from_arrays`` makes of these decoded rows:
    the same float64 arithmetic (``dequantise_row``, ``capture - base``), each value
    rounded to float32 (float16 for velocities) once, by ``struct``, as numpy does."""
    base = base_us / 1e6
    lo, step = volume.lo, volume.step
    fast = _accel.speedups
    if fast is not None:
        records = fast.update_records(base_us, streams, off, rows, lo, step)
        dtype = UPDATE_VELOCITY_DTYPE if len(rows[0]) == 13 else UPDATE_DTYPE
        return PoseUpdate._trusted(number, base, np.frombuffer(records, dtype))
    parts = []
    if len(rows[0]) == 13:
        pack = _VELOCITY_RECORD.pack
        for s, o, r in zip(streams, off, rows, strict=True):
            parts.append(
                pack(s, (base - o / 1000.0) - base, *dequantise_row(r, lo, step), *velocity_row(r))
            )
        entries = np.frombuffer(b"".join(parts), UPDATE_VELOCITY_DTYPE)
    else:
        pack = _RECORD.pack
        for s, o, r in zip(streams, off, rows, strict=True):
            parts.append(pack(s, (base - o / 1000.0) - base, *dequantise_row(r, lo, step)))
        entries = np.frombuffer(b"".join(parts), UPDATE_DTYPE)
    return PoseUpdate._trusted(number, base, entries)


class SnapshotDecoder:
    """The client's half of compact snapshots: relay frame -> ``Snapshot``.

    Baselines are the codes last received for each (user, stream); a frame coded
    against others raises ``BaselineMismatch`` (fatal ``bad-baseline``). They are
    kept when a user leaves: the relay's ids are reused only after key entries,
    and ids come from bounded pools, so the table stays small.
    """

    def __init__(self, volume: Volume) -> None:
        self.volume = volume
        self.baselines: dict[tuple[int, int], list[int]] = {}

    def decode(self, data: bytes | bytearray | memoryview) -> Snapshot:
        """The snapshot in ``data``; raises ``RemoteProtocolError``."""
        try:
            frame = decode_relay_snapshot(bytes(data), self.volume, self.baselines)
        except ProtocolViolation as exc:
            raise RemoteProtocolError(exc.code, exc.message, in_reply_to="snapshot") from None
        frame.remember(self.baselines)
        poses, velocities = frame.arrays()
        return Snapshot.from_arrays(
            frame.tick,
            frame.base_time,
            frame.users,
            frame.streams,
            frame.capture_times,
            poses,
            velocities=velocities,
        )
