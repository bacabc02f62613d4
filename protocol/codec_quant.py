"""Quantisers of the compact pose codec: poses (and velocities) to integer codes and back.

The codes of a pose are one int64 row ``[idx, a, b, c, px, py, pz]`` (plus
``[vx, vy, vz, wx, wy, wz]`` in the velocity variant); ``protocol.codec``'s module
docstring gives each quantiser's step and error. Also here: the room
:class:`Volume`, the check that a code row is in range (shared by the encoder,
which raises ``LocalProtocolError``, and the decoder, ``RemoteProtocolError``), and
the integer-only rotation predictor the delta frames are coded against.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from posecast.protocol.errors import ErrorCode, LocalProtocolError, RemoteProtocolError
from posecast.protocol.limits import QUAT_NORM_TOLERANCE

__all__ = [
    "ANG_STEP",
    "DEFAULT_VOLUME",
    "LIN_STEP",
    "POSITION_STEP_MAX",
    "ROTATION_BITS",
    "ROTATION_ERROR_MAX_DEG",
    "VEL_LIMIT",
    "M",
    "Volume",
    "codes_problem",
    "dequantise",
    "dequantise_row",
    "float_array",
    "local_error",
    "predict_rotation",
    "quantise",
    "remote_error",
    "velocity_row",
]

I64 = NDArray[np.int64]

#: Bits of each smallest-three component.
ROTATION_BITS = 13
#: Largest smallest-three component code (4095).
M = (1 << (ROTATION_BITS - 1)) - 1
_ROT_SCALE = math.sqrt(2.0) * M
#: Worst-case rotation error of the quantiser, degrees (4 sqrt(3) * step / 2).
ROTATION_ERROR_MAX_DEG = math.degrees(2.0 * math.sqrt(3.0) / _ROT_SCALE)
#: Largest position step a Volume may use, metres.
POSITION_STEP_MAX = 0.0005
#: Velocity steps (m/s, rad/s) and the clamp of both (in those units).
LIN_STEP = 2.0**-9
ANG_STEP = 2.0**-8
VEL_LIMIT = 64.0
_LIN_CODE_MAX = round(VEL_LIMIT / LIN_STEP)
_ANG_CODE_MAX = round(VEL_LIMIT / ANG_STEP)
# The three indices that are not idx, in order.
_OTHERS = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]], np.int64)
_NORM_LO = (1.0 - QUAT_NORM_TOLERANCE) ** 2
_NORM_HI = (1.0 + QUAT_NORM_TOLERANCE) ** 2


#: Up to this many rows, quantise / dequantise / codes_problem loop in Python.
_SMALL = 30
_OTHERS_T = ((1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2))


def local_error(code: ErrorCode, message: str) -> LocalProtocolError:
    """This side built something invalid."""
    return LocalProtocolError(code, message)


def remote_error(code: ErrorCode, message: str) -> RemoteProtocolError:
    """The peer sent something invalid."""
    return RemoteProtocolError(code, message)


@dataclass(frozen=True, slots=True)
class Volume:
    """The room's bounded position volume, metres (min and max per axis, inclusive)."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]

    def __post_init__(self) -> None:
        lo = tuple(float(x) for x in self.lo)
        hi = tuple(float(x) for x in self.hi)
        if len(lo) != 3 or len(hi) != 3:
            raise local_error(ErrorCode.BAD_MESSAGE, "volume needs 3 minima and 3 maxima")
        for a, b in zip(lo, hi, strict=True):
            if not (math.isfinite(a) and math.isfinite(b) and a < b and b - a <= 4096.0):
                raise local_error(
                    ErrorCode.BAD_MESSAGE, "volume axis must have lo < hi <= lo + 4096"
                )
        object.__setattr__(self, "lo", lo)
        object.__setattr__(self, "hi", hi)

    @property
    def bits(self) -> tuple[int, int, int]:
        """Bits per axis of a key position."""
        return _geometry(self.lo, self.hi)[0]

    @property
    def step(self) -> tuple[float, float, float]:
        """Quantisation step per axis, metres (<= POSITION_STEP_MAX)."""
        return _geometry(self.lo, self.hi)[1]


_Geometry = tuple[tuple[int, int, int], tuple[float, float, float]]
#: (bits, step) by (lo, hi): every codec call asks for them, a few logs each time.
_GEOMETRY: dict[tuple[tuple[float, ...], tuple[float, ...]], _Geometry] = {}


def _geometry(lo: tuple[float, ...], hi: tuple[float, ...]) -> _Geometry:
    got = _GEOMETRY.get((lo, hi))
    if got is None:
        b = [
            max(1, math.ceil(math.log2((h - low) / POSITION_STEP_MAX + 1.0)))
            for low, h in zip(lo, hi, strict=True)
        ]
        s = [(h - low) / ((1 << n) - 1) for low, h, n in zip(lo, hi, b, strict=True)]
        if len(_GEOMETRY) < 256:  # volumes come from configuration: few of them
            _GEOMETRY[(lo, hi)] = got = ((b[0], b[1], b[2]), (s[0], s[1], s[2]))
        else:
            return (b[0], b[1], b[2]), (s[0], s[1], s[2])
    return got


#: A 16 m x 6 m x 16 m room (x, z in [-8, 8], y in [-2, 4]): 15 + 14 + 15 bits.
DEFAULT_VOLUME = Volume((-8.0, -2.0, -8.0), (8.0, 4.0, 8.0))


def float_array(name: str, value: ArrayLike, shape: tuple[int, ...]) -> NDArray[np.float64]:
    """``value`` as float64 of exactly ``shape``, else ``bad-message``."""
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise local_error(ErrorCode.BAD_MESSAGE, f"{name} must be an array of numbers") from None
    if array.shape != shape:
        raise local_error(
            ErrorCode.BAD_MESSAGE, f"{name} must have shape {shape}, got {array.shape}"
        )
    return array


def _quantise_rotation(q: NDArray[np.float64]) -> tuple[I64, I64]:
    """Largest index (n,) and the three small components (n, 3) of unit quaternions."""
    n = q.shape[0]
    idx = np.argmax(np.abs(q), axis=1)
    sign = np.where(q[np.arange(n), idx] < 0.0, -1.0, 1.0)
    small = np.take_along_axis(q * sign[:, None], _OTHERS[idx], axis=1)
    rot = np.clip(np.rint(small * _ROT_SCALE), -M, M).astype(np.int64)
    return idx.astype(np.int64), rot


def _quantise_position(xyz: NDArray[np.float64], volume: Volume) -> I64:
    pos = np.rint((xyz - np.array(volume.lo)) / np.array(volume.step))
    top = (np.int64(1) << np.array(volume.bits, np.int64)) - 1
    if xyz.shape[0] and (bool((pos < 0).any()) or bool((pos > top).any())):
        bad = np.flatnonzero(((pos < 0) | (pos > top)).any(axis=1))[0]
        raise local_error(
            ErrorCode.BAD_POSE,
            f"position {xyz[bad].tolist()} outside the room volume {volume.lo}..{volume.hi}",
        )
    out: I64 = pos.astype(np.int64)
    return out


def quantise(poses: ArrayLike, volume: Volume, velocities: ArrayLike | None = None) -> I64:
    """Codes (n, 7) or (n, 13) of poses (n, 7) [and velocities (n, 6)]; see the module doc.

    Raises ``LocalProtocolError``: ``bad-pose`` for NaN/inf, a quaternion norm off
    1 by more than QUAT_NORM_TOLERANCE, or a position outside ``volume``;
    ``bad-velocity`` for NaN/inf velocities.
    """
    raw = np.asarray(poses, dtype=np.float64)
    if raw.ndim != 2 or raw.shape[1] != 7:
        raise local_error(ErrorCode.BAD_MESSAGE, f"poses must have shape (n, 7), got {raw.shape}")
    n = raw.shape[0]
    if not np.isfinite(raw).all():
        raise local_error(ErrorCode.BAD_POSE, "non-finite pose")
    q = raw[:, 3:]
    norm2 = np.einsum("ij,ij->i", q, q)
    if n and not (float(norm2.min()) >= _NORM_LO and float(norm2.max()) <= _NORM_HI):
        raise local_error(ErrorCode.BAD_POSE, "quaternion not unit")
    if 0 < n <= _SMALL:
        small = _quantise_small(raw, norm2, volume)
        if small is not None:
            if velocities is None:
                return np.array(small, np.int64)
            return _with_velocities(small, velocities)
    idx, rot = _quantise_rotation(q / np.sqrt(norm2)[:, None])
    pos = _quantise_position(raw[:, :3], volume)
    columns = [idx[:, None], rot, pos]
    if velocities is not None:
        vel = _velocity_array(velocities, n)
        vel = np.clip(vel, -VEL_LIMIT, VEL_LIMIT)
        columns.append(np.rint(vel[:, :3] / LIN_STEP).astype(np.int64))
        columns.append(np.rint(vel[:, 3:] / ANG_STEP).astype(np.int64))
    return np.concatenate(columns, axis=1)


def dequantise(
    codes: I64, volume: Volume
) -> tuple[NDArray[np.float32], NDArray[np.float32] | None]:
    """Poses (n, 7) float32 and velocities (n, 6) float32 (or None) of valid codes."""
    n = codes.shape[0]
    if 0 < n <= _SMALL:
        return _dequantise_small(codes, volume)
    small = codes[:, 1:4].astype(np.float64) / _ROT_SCALE
    w = np.sqrt(np.maximum(0.0, 1.0 - np.einsum("ij,ij->i", small, small)))
    q = np.empty((n, 4))
    idx = codes[:, 0]
    np.put_along_axis(q, idx[:, None], w[:, None], axis=1)
    np.put_along_axis(q, _OTHERS[idx], small, axis=1)
    pos = np.array(volume.lo) + codes[:, 4:7] * np.array(volume.step)
    poses = np.concatenate([pos, q], axis=1).astype(np.float32)
    if codes.shape[1] == 7:
        return poses, None
    vel = np.concatenate([codes[:, 7:10] * LIN_STEP, codes[:, 10:13] * ANG_STEP], axis=1).astype(
        np.float32
    )
    return poses, vel


def codes_problem(codes: I64, volume: Volume) -> str | None:
    """What is out of range in code rows (n, 7 or 13), or None if they are valid."""
    if not codes.shape[0]:
        return None
    if codes.shape[0] <= _SMALL:
        return codes_problem_rows(codes.tolist(), volume)
    if int(codes[:, 0].min()) < 0 or int(codes[:, 0].max()) > 3:
        return "rotation index out of range"
    abc = codes[:, 1:4]
    if int(np.abs(abc).max()) > M or int(np.einsum("ij,ij->i", abc, abc).max()) > 2 * M * M:
        return "rotation out of range"
    top = (np.int64(1) << np.array(volume.bits, np.int64)) - 1
    pos = codes[:, 4:7]
    if bool((pos < 0).any()) or bool((pos > top).any()):
        return "position outside the room volume"
    if codes.shape[1] == 13:
        lin = int(np.abs(codes[:, 7:10]).max())
        ang = int(np.abs(codes[:, 10:13]).max())
        if lin > _LIN_CODE_MAX or ang > _ANG_CODE_MAX:
            return "velocity out of range"
    return None


def predict_rotation(base: I64, idx: I64) -> I64:
    """The baseline rotations' three small components re-expressed with largest index idx.

    Integer arithmetic only (the dropped component is the rounded integer square
    root of 2 * 4095**2 - a**2 - b**2 - c**2), so every implementation agrees.
    """
    n = base.shape[0]
    abc = base[:, 1:4]
    rest = np.maximum(0, 2 * M * M - np.einsum("ij,ij->i", abc, abc))
    # round(sqrt(r)) = (isqrt(4 r) + 1) // 2; float sqrt is exact enough below 2**52.
    big = (np.floor(np.sqrt(4.0 * rest)).astype(np.int64) + 1) // 2
    full = np.empty((n, 4), np.int64)
    np.put_along_axis(full, base[:, 0:1], big[:, None], axis=1)
    np.put_along_axis(full, _OTHERS[base[:, 0]], abc, axis=1)
    sign = np.where(full[np.arange(n), idx] < 0, -1, 1)
    pred = np.take_along_axis(full * sign[:, None], _OTHERS[idx], axis=1)
    return np.clip(pred, -M, M)


def codes_problem_rows(rows: list[list[int]], volume: Volume) -> str | None:
    """:func:`codes_problem` of code rows as Python ints (the small frames' path)."""
    top = [(1 << b) - 1 for b in volume.bits]
    for check in range(4):
        for r in rows:
            if check == 0 and not 0 <= r[0] <= 3:
                return "rotation index out of range"
            if check == 1 and (
                max(abs(r[1]), abs(r[2]), abs(r[3])) > M
                or r[1] * r[1] + r[2] * r[2] + r[3] * r[3] > 2 * M * M
            ):
                return "rotation out of range"
            if check == 2 and not (
                0 <= r[4] <= top[0] and 0 <= r[5] <= top[1] and 0 <= r[6] <= top[2]
            ):
                return "position outside the room volume"
            if (
                check == 3
                and len(r) == 13
                and (
                    max(abs(v) for v in r[7:10]) > _LIN_CODE_MAX
                    or max(abs(v) for v in r[10:13]) > _ANG_CODE_MAX
                )
            ):
                return "velocity out of range"
    return None


def _velocity_array(velocities: ArrayLike, n: int) -> NDArray[np.float64]:
    vel = float_array("velocities", velocities, (n, 6))
    if not np.isfinite(vel).all():
        raise local_error(ErrorCode.BAD_VELOCITY, "non-finite velocity")
    return vel


def _with_velocities(codes: list[list[int]], velocities: ArrayLike) -> I64:
    for row, v in zip(codes, _velocity_array(velocities, len(codes)).tolist(), strict=True):
        c = [min(VEL_LIMIT, max(-VEL_LIMIT, x)) for x in v]
        row += [round(x / LIN_STEP) for x in c[:3]] + [round(x / ANG_STEP) for x in c[3:]]
    return np.array(codes, np.int64)


def _quantise_small(
    raw: NDArray[np.float64], norm2: NDArray[np.float64], volume: Volume
) -> list[list[int]] | None:
    """:func:`quantise` of a few checked rows with Python floats (the same operations,
    so the same codes); None for a position outside the volume (numpy path raises)."""
    lo, step = volume.lo, volume.step
    top = [(1 << b) - 1 for b in volume.bits]
    rows = []
    for r, n2 in zip(raw.tolist(), norm2.tolist(), strict=True):
        s = math.sqrt(n2)
        q = [r[3] / s, r[4] / s, r[5] / s, r[6] / s]
        idx = 0
        for i in (1, 2, 3):
            if abs(q[i]) > abs(q[idx]):
                idx = i
        sign = -1.0 if q[idx] < 0.0 else 1.0
        row = [idx] + [min(M, max(-M, round(q[o] * sign * _ROT_SCALE))) for o in _OTHERS_T[idx]]
        for a in range(3):
            p = round((r[a] - lo[a]) / step[a])
            if not 0 <= p <= top[a]:
                return None
            row.append(p)
        rows.append(row)
    return rows


def dequantise_row(
    r: list[int], lo: tuple[float, float, float], step: tuple[float, float, float]
) -> list[float]:
    """The pose (7 Python floats, before the float32 cast) of one valid code row:
    :func:`dequantise`'s arithmetic, in the same order (numpy's einsum of a
    contiguous (n, 3) array sums (x x + z z) + y y)."""
    x, y, z = r[1] / _ROT_SCALE, r[2] / _ROT_SCALE, r[3] / _ROT_SCALE
    q = [0.0, 0.0, 0.0, 0.0]
    q[r[0]] = math.sqrt(max(0.0, 1.0 - ((x * x + z * z) + y * y)))
    a, b, c = _OTHERS_T[r[0]]
    q[a], q[b], q[c] = x, y, z
    return [lo[0] + r[4] * step[0], lo[1] + r[5] * step[1], lo[2] + r[6] * step[2], *q]


def velocity_row(r: list[int]) -> list[float]:
    """The velocity (6 Python floats) of one valid code row of 13."""
    return [v * LIN_STEP for v in r[7:10]] + [v * ANG_STEP for v in r[10:13]]


def _dequantise_small(
    codes: I64, volume: Volume
) -> tuple[NDArray[np.float32], NDArray[np.float32] | None]:
    """:func:`dequantise` of a few rows with Python floats (:func:`dequantise_row`)."""
    lo, step = volume.lo, volume.step
    poses = []
    vels = []
    for r in codes.tolist():
        poses.append(dequantise_row(r, lo, step))
        if len(r) == 13:
            vels.append(velocity_row(r))
    out = np.array(poses, np.float64).astype(np.float32)
    if codes.shape[1] == 7:
        return out, None
    return out, np.array(vels, np.float64).astype(np.float32)
