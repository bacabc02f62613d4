"""Compact pose codec, sans-I/O: quantised key and delta frames for snapshots and updates.

Sessions use it through ``protocol._compact`` (updates) and ``protocol.codec_relay``
(the relay's snapshots, a second layout of the same fields).
See ``docs/concepts/codec.md`` for the measured sizes and errors on the real traces. The
work is split: quantisers and :class:`Volume` in ``protocol.codec_quant``, the
frame layout below in ``protocol.codec_frame``, bit packing in ``protocol.bits``;
this module is the public API (every public name is importable from here).

Quantisation (the *codes* of a pose: one int64 row, the unit of exactness)::

    [idx, a, b, c, px, py, pz]            + [vx, vy, vz, wx, wy, wz] (velocity variant)

- rotation: smallest three. ``idx`` (0..3) is the index of the largest |component|
  of the w-first quaternion, the sign is folded so that it is positive, and the
  other three (in order) are ``round(x * sqrt(2) * 4095)`` in [-4095, 4095]
  (13 bits: step 1/(4095 sqrt 2) = 1.73e-4). The rotation error estimate
  4 sqrt(3) * step / 2 = 5.98e-4 rad = 0.0343 deg is not a strict bound: 0.0376
  deg was measured on a real trace (``tests/scenarios/test_codec_qoe.py``);
  the target is 0.05 deg.
- position: ``round((p - lo) / step)`` per axis of a :class:`Volume`, with
  ``step = (hi - lo) / (2**bits - 1) <= 0.5 mm`` (error <= 0.25 mm). A position
  more than half a step outside the volume is refused (``bad-pose``), never wrapped.
- velocity: linear in steps of 2**-9 m/s (error <= 0.98 mm/s), angular in steps of
  2**-8 rad/s (error <= 0.112 deg/s), finite values clamped to +-64; NaN/inf
  refused (``bad-velocity``).
- capture time: ``round((base_time - t) * 1000)`` ms before the frame's base time
  (error <= 0.5 ms), base time itself in whole microseconds.

``decode(encode(x))`` gives back the codes of ``x`` exactly, hence the poses of
:func:`dequantise` bit for bit.

Frame layout (not msgpack: the first byte 0xC1 is the one byte msgpack never uses,
so a receiver tells the two apart from the first byte)::

    0xC1  flags            bit 0: update (else snapshot), bit 1: velocities,
                           bit 2: class split, bits 4-7: codec version (1)
    uvarint  tick | seq
    svarint  base time, integer microseconds (zigzag LEB128)
    uvarint  n_key, uvarint n_delta
    check    CRC-32 of the baselines' codes (int32 LE, delta entries in order),
             present iff n_delta > 0: u32 LE in a snapshot, its low 16 bits
             (u16 LE) in an update
    nibbles  Exp-Golomb orders k, 4 bits each, high nibble first, padded to a byte:
             key section:   t_first [vlin, vang]
             delta section: t_first rot0 rot1 pos0 pos1 [vlin0 vlin1 vang0 vang1]
             (0/1: class of the entry, 0 = stream 0 (head), 1 = other streams;
             without the class-split flag every entry is class 0)
    bits     key section columns, then delta section columns, MSB first,
             zero-padded to a byte; no trailing bytes

Each section lists entries sorted by (user, stream), as columns (see
``protocol.bits``: "EG k" is Exp-Golomb of order k, "zz" zigzag):

    ug      EG 0        user - previous user (snapshots only; first: user)
    sg      EG 0        stream (new user) or stream - previous stream - 1
    t_first EG k, zz    time offset (ms) of the first entry of each user
    t_same  EG 0, zz    offset - previous entry's offset, for the other entries
    key:    idx: 2 bits; a, b, c: 13 bits each (+4095); px, py, pz: Volume.bits;
            velocities: EG zz, vlin / vang
    delta:  idx: EG 0 of (idx - baseline idx) mod 4; then per column, class 0
            entries then class 1 entries: a, b, c (EG zz of the difference to the
            baseline rotation re-expressed with the new idx, integer arithmetic
            only), px, py, pz (EG zz of the difference), velocities (same)

The server keeps, per group of subscribers, the codes it wrote last for each
stream (``PoseFrame.remember``); a stream with no new pose since is left out and
costs nothing. A decoder missing a baseline, or holding other baselines than
the encoder used (CRC mismatch), raises :class:`BaselineMismatch` and shows
nothing of that frame.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numpy.typing import ArrayLike, NDArray

from posecast.protocol import _accel
from posecast.protocol.codec_fast import decode_small, encode_small
from posecast.protocol.codec_frame import (
    CODEC_MAGIC,
    CODEC_VERSION,
    F_UPDATE,
    F_VELOCITY,
    BaselineMismatch,
    Encoded,
    PoseFrame,
    decode_frame,
    encode_frame,
)
from posecast.protocol.codec_quant import (
    DEFAULT_VOLUME,
    POSITION_STEP_MAX,
    ROTATION_BITS,
    ROTATION_ERROR_MAX_DEG,
    Volume,
    codes_problem,
    dequantise,
    float_array,
    local_error,
    quantise,
)
from posecast.protocol.errors import ErrorCode

__all__ = [
    "ACCELERATOR_NOTICE",  # noqa: F822 (the module __getattr__ below)
    "CODEC_MAGIC",
    "CODEC_VERSION",
    "DEFAULT_VOLUME",
    "IMPLEMENTATION",  # noqa: F822 (the module __getattr__ below)
    "POSITION_STEP_MAX",
    "ROTATION_BITS",
    "ROTATION_ERROR_MAX_DEG",
    "BaselineMismatch",
    "Encoded",
    "PoseFrame",
    "Volume",
    "decode_snapshot",
    "decode_update",
    "dequantise",
    "encode_delta_snapshot",
    "encode_key_snapshot",
    "encode_snapshot_codes",
    "encode_update",
    "encode_update_codes",
    "quantise",
]

I64 = NDArray[np.int64]


def __getattr__(name: str) -> str:
    # IMPLEMENTATION: what runs the hot paths, "compiled (C accelerator)" or "pure
    # Python (...)" (``protocol._accel``); read at each access, as tests switch it.
    if name == "IMPLEMENTATION":
        return _accel.IMPLEMENTATION
    # ACCELERATOR_NOTICE: why the accelerator does not run though not turned off, or "".
    if name == "ACCELERATOR_NOTICE":
        return _accel.NOTICE
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _ids(value: ArrayLike, n: int, name: str) -> I64:
    array = np.asarray(value)
    if array.shape != (n,) or (n and array.dtype.kind not in "iu"):
        raise local_error(ErrorCode.BAD_MESSAGE, f"{name} must be {n} ints")
    array = array.astype(np.int64)
    if n and (int(array.min()) < 0 or int(array.max()) > 0xFFFF):
        raise local_error(ErrorCode.BAD_MESSAGE, f"{name} must be in [0, 65535]")
    return array


def _check_codes(codes: ArrayLike, volume: Volume) -> I64:
    array = np.asarray(codes)
    if array.ndim != 2 or array.shape[1] not in (7, 13) or array.dtype.kind not in "iu":
        raise local_error(ErrorCode.BAD_MESSAGE, "codes must be ints of shape (n, 7) or (n, 13)")
    array = array.astype(np.int64)
    problem = codes_problem(array, volume)
    if problem:
        raise local_error(ErrorCode.BAD_POSE, problem)
    return array


def encode_snapshot_codes(
    tick: int,
    base_time: float,
    users: ArrayLike,
    streams: ArrayLike,
    capture_times: ArrayLike,
    codes: ArrayLike,
    volume: Volume,
    baselines: Mapping[tuple[int, int], I64] | None = None,
    *,
    split: bool = True,
) -> Encoded:
    """A snapshot of already quantised poses (a relay forwards what it decoded).

    Streams with a baseline in ``baselines`` (keyed ``(user, stream)``) are
    delta-coded, the others absolute; leave out streams with nothing new.
    """
    code_array = _check_codes(codes, volume)
    n = code_array.shape[0]
    flags = F_VELOCITY if code_array.shape[1] == 13 else 0
    args = (
        flags,
        tick,
        float(base_time),
        _ids(users, n, "users"),
        _ids(streams, n, "streams"),
        float_array("capture_times", capture_times, (n,)),
        code_array,
        volume,
        baselines,
        split,
    )
    return encode_small(*args) or encode_frame(*args)


def encode_key_snapshot(
    tick: int,
    base_time: float,
    users: ArrayLike,
    streams: ArrayLike,
    capture_times: ArrayLike,
    poses: ArrayLike,
    volume: Volume,
    velocities: ArrayLike | None = None,
) -> Encoded:
    """A key snapshot: every pose absolute (users, streams, times (n,); poses (n, 7))."""
    codes = quantise(poses, volume, velocities)
    return encode_snapshot_codes(tick, base_time, users, streams, capture_times, codes, volume)


def encode_delta_snapshot(
    tick: int,
    base_time: float,
    users: ArrayLike,
    streams: ArrayLike,
    capture_times: ArrayLike,
    poses: ArrayLike,
    volume: Volume,
    baselines: Mapping[tuple[int, int], I64],
    velocities: ArrayLike | None = None,
) -> Encoded:
    """A snapshot delta-coded against ``baselines``; streams without one go absolute."""
    codes = quantise(poses, volume, velocities)
    return encode_snapshot_codes(
        tick, base_time, users, streams, capture_times, codes, volume, baselines
    )


def encode_update_codes(
    seq: int,
    base_time: float,
    streams: ArrayLike,
    capture_times: ArrayLike,
    codes: ArrayLike,
    volume: Volume,
    baselines: Mapping[int, I64] | None = None,
) -> Encoded:
    """An update (client -> server) of quantised poses; baselines keyed by stream id."""
    code_array = _check_codes(codes, volume)
    n = code_array.shape[0]
    flags = F_UPDATE | (F_VELOCITY if code_array.shape[1] == 13 else 0)
    args = (
        flags,
        seq,
        float(base_time),
        np.zeros(n, np.int64),
        _ids(streams, n, "streams"),
        float_array("capture_times", capture_times, (n,)),
        code_array,
        volume,
        baselines,
        True,
    )
    return encode_small(*args) or encode_frame(*args)


def encode_update(
    seq: int,
    base_time: float,
    streams: ArrayLike,
    capture_times: ArrayLike,
    poses: ArrayLike,
    volume: Volume,
    baselines: Mapping[int, I64] | None = None,
    velocities: ArrayLike | None = None,
) -> Encoded:
    """An update of poses (n, 7): delta against ``baselines`` where it has one."""
    codes = quantise(poses, volume, velocities)
    return encode_update_codes(seq, base_time, streams, capture_times, codes, volume, baselines)


def decode_snapshot(
    data: bytes, volume: Volume, baselines: Mapping[tuple[int, int], I64] | None = None
) -> PoseFrame:
    """Decode a snapshot frame; raises only ``RemoteProtocolError`` (with a code)."""
    return decode_small(data, volume, baselines, False) or decode_frame(
        data, volume, baselines, False
    )


def decode_update(
    data: bytes, volume: Volume, baselines: Mapping[int, I64] | None = None
) -> PoseFrame:
    """Decode an update frame; baselines keyed by stream id."""
    return decode_small(data, volume, baselines, True) or decode_frame(
        data, volume, baselines, True
    )
