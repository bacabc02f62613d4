"""Pose frames: client updates and server snapshots, packed as numpy records in msgpack bin.

Wire layout (little-endian, packed, no padding)::

    update    {"type": "update",   "seq": int,  "time": float64, "poses": bin}
              poses = records of UPDATE_DTYPE:   stream u16, dt f4, pose 7 x f4  (34 B)
              capture time = time + dt  (time: any base in server clock, usually
              the newest capture time, so dt <= 0 and small)

    snapshot  {"type": "snapshot", "tick": int, "time": float64, "poses": bin}
              poses = records of SNAPSHOT_DTYPE: user u16, stream u16, dt f4,
                                                 pose 7 x f4                   (36 B)
              time = when the server sent it; capture time = time + dt (dt <= 0)

Times travel as one float64 plus a float32 offset per pose: an offset under 8 s
keeps better than 1 us resolution, and each pose saves 4 bytes.

Velocity variant (negotiated at join: ``Join.sends_velocities`` for a client's
updates, ``Join.wants_velocities`` for the snapshots it receives)::

    update    {"type": "update",   "seq": int,  "time": float64, "vpose": bin}
              vpose = records of UPDATE_VELOCITY_DTYPE:
                      stream u16, dt f4, pose 7 x f4, velocity 6 x f2      (46 B)
    snapshot  {"type": "snapshot", "tick": int, "time": float64, "vpose": bin}
              vpose = records of SNAPSHOT_VELOCITY_DTYPE:
                      user u16, stream u16, dt f4, pose 7 x f4, velocity 6 x f2 (48 B)

The velocity is what a tracker runtime reports with the pose (OpenXR
``XrSpaceVelocity``): linear velocity of the device origin (m/s, 3) then angular
velocity (rad/s, 3), **both in the world frame** (the convention of
``interp.cubic.motor_hermite`` and ``interp.extrapolate.twist_extrapolate``), as
little-endian float16: 12 bytes a pose more. The key "vpose" is as long as
"poses", so a velocity frame is exactly the plain frame plus 12 bytes a pose
(plus one byte when the bin header grows). Encoders clamp finite velocities to
float16's range (+-65504) and leave NaN/inf as they are: sessions refuse those
as "bad-velocity".

Decoding is zero-copy: ``entries`` is ``np.frombuffer`` over the received bytes
(read-only); ``poses`` and ``streams`` are views into it, ``capture_times`` is
computed in float64. Copy before modifying.

This module owns the record layouts, the frame classes, ``encode_snapshot``
(one call per server tick, bytes shared by every subscriber), the pose checks
(finite, unit quaternion) and the bytes-per-pose figures.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any, ClassVar, Literal, Self

import msgpack
import numpy as np
from numpy.typing import ArrayLike, NDArray

from posecast.protocol._validate import U16_MAX, U63_MAX, bad, check_float, check_int
from posecast.protocol.limits import QUAT_NORM_TOLERANCE

__all__ = [
    "POSE_BYTES",
    "SNAPSHOT_DTYPE",
    "SNAPSHOT_ENTRY_SIZE",
    "SNAPSHOT_VELOCITY_DTYPE",
    "SNAPSHOT_VELOCITY_ENTRY_SIZE",
    "UPDATE_DTYPE",
    "UPDATE_ENTRY_SIZE",
    "UPDATE_VELOCITY_DTYPE",
    "UPDATE_VELOCITY_ENTRY_SIZE",
    "VELOCITY_BYTES",
    "VELOCITY_MAX",
    "ZERO_VELOCITY",
    "PoseUpdate",
    "Snapshot",
    "bytes_per_pose",
    "encode_snapshot",
    "encode_update",
    "frame_size",
    "has_velocity",
    "pack_snapshot",
    "pack_velocity_snapshot",
    "pose_problem",
    "update_records",
    "velocity_problem",
]

UPDATE_DTYPE = np.dtype([("stream", "<u2"), ("dt", "<f4"), ("pose", "<f4", (7,))])
SNAPSHOT_DTYPE = np.dtype(
    [("user", "<u2"), ("stream", "<u2"), ("dt", "<f4"), ("pose", "<f4", (7,))]
)
UPDATE_VELOCITY_DTYPE = np.dtype(
    [("stream", "<u2"), ("dt", "<f4"), ("pose", "<f4", (7,)), ("velocity", "<f2", (6,))]
)
SNAPSHOT_VELOCITY_DTYPE = np.dtype(
    [
        ("user", "<u2"),
        ("stream", "<u2"),
        ("dt", "<f4"),
        ("pose", "<f4", (7,)),
        ("velocity", "<f2", (6,)),
    ]
)
UPDATE_ENTRY_SIZE = UPDATE_DTYPE.itemsize
SNAPSHOT_ENTRY_SIZE = SNAPSHOT_DTYPE.itemsize
UPDATE_VELOCITY_ENTRY_SIZE = UPDATE_VELOCITY_DTYPE.itemsize
SNAPSHOT_VELOCITY_ENTRY_SIZE = SNAPSHOT_VELOCITY_DTYPE.itemsize
#: A pose on the wire: 7 little-endian float32.
POSE_BYTES = 28
#: A velocity on the wire: 6 little-endian float16 (linear m/s, angular rad/s, world frame).
VELOCITY_BYTES = 12
#: Largest finite float16: encoders clamp velocity components to +-VELOCITY_MAX.
VELOCITY_MAX = float(np.finfo(np.float16).max)
#: The velocity bytes of a stream whose sender reports none (all zeros).
ZERO_VELOCITY = bytes(VELOCITY_BYTES)
# The fixed heads of the entry layouts above, for the relay's byte-level path.
_UPDATE_HEAD = struct.Struct("<Hf")
_SNAPSHOT_HEAD = struct.Struct("<HHf")
# Wire key of the records: plain frames and the velocity variant (same length).
POSES_KEY = "poses"
VELOCITY_POSES_KEY = "vpose"

# |norm - 1| <= tol  <=>  (1 - tol)^2 <= norm^2 <= (1 + tol)^2, with no sqrt.
_NORM2_LO = (1.0 - QUAT_NORM_TOLERANCE) ** 2
_NORM2_HI = (1.0 + QUAT_NORM_TOLERANCE) ** 2

# Up to this many poses a plain Python loop beats numpy, whose reductions cost
# microseconds each on tiny arrays; updates (a few streams) stay on this path.
_LOOP_MAX = 32


def _floats(entries: NDArray[np.void]) -> NDArray[np.float32]:
    # dt and the 7 pose numbers are 32 contiguous bytes of every record layout:
    # view them as one (n, 8) float32 array [dt, px, py, pz, qw, qx, qy, qz].
    if not entries.flags.c_contiguous:
        entries = np.ascontiguousarray(entries)
    dtype = entries.dtype
    fields = dtype.fields
    assert fields is not None
    start: int = fields["dt"][1]
    return np.ndarray((len(entries), 8), "<f4", entries, start, (dtype.itemsize, 4))


def has_velocity(entries: NDArray[np.void]) -> bool:
    """Whether these records are of a velocity layout."""
    names = entries.dtype.names
    return names is not None and "velocity" in names


def velocity_problem(entries: NDArray[np.void]) -> str | None:
    """ "non-finite velocity" if a velocity record holds NaN or inf, else None.

    Plain records (no velocities) are always fine.
    """
    if not len(entries) or not has_velocity(entries):
        return None
    velocity = entries["velocity"]
    # float16 NaN and inf have every exponent bit set: a check on the bits is
    # exact and needs no float conversion.
    bits = np.ascontiguousarray(velocity).view("<u2")
    if bool(((bits & 0x7C00) == 0x7C00).any()):
        return "non-finite velocity"
    return None


def pose_problem(entries: NDArray[np.void]) -> str | None:
    """Why these records' poses are unusable ("non-finite pose", ...), or None if fine.

    Works on every record layout (plain and velocity); checks dt and pose are
    finite and every quaternion's norm is within QUAT_NORM_TOLERANCE of 1.
    Velocities are checked by :func:`velocity_problem`.
    """
    n = len(entries)
    if n == 0:
        return None
    floats = _floats(entries)
    if n <= _LOOP_MAX:
        for dt, px, py, pz, qw, qx, qy, qz in floats.tolist():
            # A sum is finite exactly when every term is (inf - inf is NaN).
            if not math.isfinite(dt + px + py + pz + qw + qx + qy + qz):
                return "non-finite pose"
            if not _NORM2_LO <= qw * qw + qx * qx + qy * qy + qz * qz <= _NORM2_HI:
                return "quaternion not unit"
        return None
    values = floats.astype(np.float64)
    # inf - inf inside the sum warns, and pytest turns warnings into errors;
    # the NaN it yields is exactly the signal wanted here.
    with np.errstate(invalid="ignore", over="ignore"):
        # float64 sums of float32 values cannot overflow: finite iff all terms are.
        if not math.isfinite(float(values.sum())):
            return "non-finite pose"
        quats = values[:, 4:]
        norm2 = np.einsum("ij,ij->i", quats, quats)
    if not (float(norm2.min()) >= _NORM2_LO and float(norm2.max()) <= _NORM2_HI):
        return "quaternion not unit"
    return None


def _u16(name: str, value: ArrayLike, n: int) -> NDArray[np.int64]:
    array = np.asarray(value)
    if array.shape != (n,):
        raise bad(name, "must be a 1-d array with one id per pose")
    if array.size and (
        array.dtype.kind not in "iu" or int(array.min()) < 0 or int(array.max()) > U16_MAX
    ):
        raise bad(name, f"must hold ints in [0, {U16_MAX}]")
    return array.astype(np.int64, copy=False)


def _float_array(name: str, value: ArrayLike) -> NDArray[np.float64]:
    try:
        return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise bad(name, "must be an array of numbers") from None


def _times(name: str, value: ArrayLike, n: int) -> NDArray[np.float64]:
    array = _float_array(name, value)
    if array.shape != (n,):
        raise bad(name, f"must have shape ({n},), got {array.shape}")
    return array


def _poses(value: ArrayLike) -> NDArray[np.float64]:
    array = _float_array("poses", value)
    if array.ndim != 2 or array.shape[1] != 7:
        raise bad("poses", f"must have shape (n, 7), got {array.shape}")
    return array


def _velocities(value: ArrayLike, n: int) -> NDArray[np.float16]:
    array = _float_array("velocities", value)
    if array.shape != (n, 6):
        raise bad("velocities", f"must have shape ({n}, 6), got {array.shape}")
    # Clamp finite values to float16's range (65520 and above would round to
    # inf); NaN and inf stay, for the receiver's check to refuse.
    with np.errstate(invalid="ignore"):
        clamped = np.where(np.isfinite(array), np.clip(array, -VELOCITY_MAX, VELOCITY_MAX), array)
    return clamped.astype("<f2")


def _base_time(base_time: float | None, capture_times: NDArray[np.float64]) -> float:
    if base_time is not None:
        return check_float("base time", base_time)
    # The newest capture time keeps every float32 offset small and <= 0.
    if len(capture_times) and np.isfinite(capture_times).all():
        return float(capture_times.max())
    return 0.0


def _check_entries(where: str, entries: object, dtypes: tuple[np.dtype, ...], label: str) -> None:
    if not isinstance(entries, np.ndarray) or entries.dtype not in dtypes:
        raise bad(where, f"must be an array of {label} records")
    if entries.ndim != 1:
        raise bad(where, "must be 1-d")


def _fill_records(
    entries: NDArray[np.void],
    times: NDArray[np.float64],
    base: float,
    poses: NDArray[np.float64],
    velocities: NDArray[np.float16] | None,
) -> None:
    # Values beyond float32 become inf without a warning; the receiver's
    # pose check reports them as "bad-pose".
    with np.errstate(over="ignore", invalid="ignore"):
        entries["dt"] = times - base
        entries["pose"] = poses
    if velocities is not None:
        entries["velocity"] = velocities


class _PoseRecords:
    """What both pose frames share: a counter, a server time and one record per pose.

    ``_COUNTER`` names the counter field (also its wire key), ``_TIME`` the
    field of the server time the records' ``dt`` offsets count from.
    """

    __slots__ = ()
    TYPE: ClassVar[str]
    _COUNTER: ClassVar[str]
    _TIME: ClassVar[str]
    entries: NDArray[np.void]

    @classmethod
    def _trusted(cls, counter: int, time: float, entries: NDArray[np.void]) -> Self:
        # The decoder has checked every field already; skipping __post_init__ (and
        # the frozen __setattr__, for the slots' own setters) saves a few
        # microseconds per frame on the server's hottest path.
        self = object.__new__(cls)
        setters = _SETTERS.get(cls)
        if setters is None:
            object.__setattr__(self, cls._COUNTER, counter)
            object.__setattr__(self, cls._TIME, time)
            object.__setattr__(self, "entries", entries)
        else:
            setters[0](self, counter)
            setters[1](self, time)
            setters[2](self, entries)
        return self

    def _head(self) -> tuple[int, float]:
        counter: int = getattr(self, self._COUNTER)
        time: float = getattr(self, self._TIME)
        return counter, time

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, type(self)):
            return NotImplemented
        return (*self._head(), self.entries.tobytes()) == (*other._head(), other.entries.tobytes())

    __hash__ = None  # type: ignore[assignment]

    def __len__(self) -> int:
        return len(self.entries)

    @property
    def capture_times(self) -> NDArray[np.float64]:
        """Capture times in server time, (n,) float64."""
        return self.entries["dt"].astype(np.float64) + self._head()[1]

    def to_wire(self) -> dict[str, object]:
        """The msgpack map for this frame."""
        counter, time = self._head()
        return {
            "type": self.TYPE,
            self._COUNTER: counter,
            "time": time,
            _key(self.entries): self.entries.tobytes(),
        }

    @property
    def streams(self) -> NDArray[np.uint16]:
        """Stream ids, (n,) view."""
        return self.entries["stream"]

    @property
    def poses(self) -> NDArray[np.float32]:
        """Poses [px, py, pz, qw, qx, qy, qz], (n, 7) float32 view."""
        return self.entries["pose"]

    @property
    def has_velocities(self) -> bool:
        """Whether this is the velocity variant."""
        return has_velocity(self.entries)

    @property
    def velocities(self) -> NDArray[np.float16] | None:
        """Velocities [vx, vy, vz, wx, wy, wz] (m/s, rad/s, world), (n, 6) float16 view."""
        return self.entries["velocity"] if self.has_velocities else None


@dataclass(frozen=True, slots=True, eq=False)
class PoseUpdate(_PoseRecords):
    """Client -> server: the latest pose of some of the user's streams.

    Build one with ``PoseUpdate.from_arrays``; a received one wraps the frame's
    bytes without copying.
    """

    TYPE: ClassVar[str] = "update"
    _COUNTER: ClassVar[str] = "seq"
    _TIME: ClassVar[str] = "base_time"
    seq: int
    """Sender's sequence number, increasing by one per update."""
    base_time: float
    """Server-clock time the offsets count from."""
    entries: NDArray[np.void]
    """Records of UPDATE_DTYPE (stream, dt, pose) or UPDATE_VELOCITY_DTYPE (+ velocity)."""

    def __post_init__(self) -> None:
        check_int("update.seq", self.seq, 0, U63_MAX)
        object.__setattr__(self, "base_time", check_float("update.time", self.base_time))
        dtypes = (UPDATE_DTYPE, UPDATE_VELOCITY_DTYPE)
        _check_entries("update.poses", self.entries, dtypes, "UPDATE_DTYPE")

    @classmethod
    def from_arrays(
        cls,
        seq: int,
        streams: ArrayLike,
        capture_times: ArrayLike,
        poses: ArrayLike,
        base_time: float | None = None,
        velocities: ArrayLike | None = None,
    ) -> PoseUpdate:
        """Pack stream ids (n,), capture times (n,) in server time and poses (n, 7).

        With ``velocities`` (n, 6: linear m/s, angular rad/s, world frame) the
        update is of the velocity variant.
        """
        pose_array = _poses(poses)
        n = len(pose_array)
        stream_array = _u16("streams", streams, n)
        times = _times("capture_times", capture_times, n)
        base = _base_time(base_time, times)
        vel = None if velocities is None else _velocities(velocities, n)
        entries = np.empty(n, dtype=UPDATE_DTYPE if vel is None else UPDATE_VELOCITY_DTYPE)
        entries["stream"] = stream_array
        _fill_records(entries, times, base, pose_array, vel)
        return cls(seq, base, entries)


@dataclass(frozen=True, slots=True, eq=False)
class Snapshot(_PoseRecords):
    """Server -> client: the latest pose of every stream the subscriber is due.

    The server builds the bytes once per tick with ``encode_snapshot``; clients
    receive this class from ``ClientSession.receive_data``.
    """

    TYPE: ClassVar[str] = "snapshot"
    _COUNTER: ClassVar[str] = "tick"
    _TIME: ClassVar[str] = "send_time"
    tick: int
    """The room's tick number."""
    send_time: float
    """Server time when the snapshot was built."""
    entries: NDArray[np.void]
    """Records of SNAPSHOT_DTYPE (user, stream, dt, pose) or SNAPSHOT_VELOCITY_DTYPE."""

    def __post_init__(self) -> None:
        check_int("snapshot.tick", self.tick, 0, U63_MAX)
        object.__setattr__(self, "send_time", check_float("snapshot.time", self.send_time))
        dtypes = (SNAPSHOT_DTYPE, SNAPSHOT_VELOCITY_DTYPE)
        _check_entries("snapshot.poses", self.entries, dtypes, "SNAPSHOT_DTYPE")

    @classmethod
    def from_arrays(
        cls,
        tick: int,
        send_time: float,
        users: ArrayLike,
        streams: ArrayLike,
        capture_times: ArrayLike,
        poses: ArrayLike,
        velocities: ArrayLike | None = None,
    ) -> Snapshot:
        """Pack user ids (n,), stream ids (n,), capture times (n,) and poses (n, 7).

        With ``velocities`` (n, 6) the snapshot is of the velocity variant.
        """
        pose_array = _poses(poses)
        n = len(pose_array)
        send = check_float("send_time", send_time)
        vel = None if velocities is None else _velocities(velocities, n)
        entries = np.empty(n, dtype=SNAPSHOT_DTYPE if vel is None else SNAPSHOT_VELOCITY_DTYPE)
        entries["user"] = _u16("users", users, n)
        entries["stream"] = _u16("streams", streams, n)
        times = _times("capture_times", capture_times, n)
        _fill_records(entries, times, send, pose_array, vel)
        return cls(tick, send, entries)

    @property
    def users(self) -> NDArray[np.uint16]:
        """User ids, (n,) view."""
        return self.entries["user"]


#: The slots' setters of each pose frame class (counter, time, entries), for _trusted.
_SETTERS: dict[type, tuple[Callable[[Any, Any], None], ...]] = {
    c: tuple(c.__dict__[name].__set__ for name in (c._COUNTER, c._TIME, "entries"))
    for c in (PoseUpdate, Snapshot)
}


def _key(entries: NDArray[np.void]) -> str:
    return VELOCITY_POSES_KEY if has_velocity(entries) else POSES_KEY


def encode_update(
    seq: int,
    streams: ArrayLike,
    capture_times: ArrayLike,
    poses: ArrayLike,
    base_time: float | None = None,
    velocities: ArrayLike | None = None,
) -> bytes:
    """Frame bytes of one update, without a session (no ownership or pose checks).

    With ``velocities`` (n, 6) the velocity variant.
    """
    update = PoseUpdate.from_arrays(seq, streams, capture_times, poses, base_time, velocities)
    return _pack(update.to_wire())


def encode_snapshot(
    tick: int,
    send_time: float,
    users: ArrayLike,
    streams: ArrayLike,
    capture_times: ArrayLike,
    poses: ArrayLike,
    velocities: ArrayLike | None = None,
) -> bytes:
    """Frame bytes of one snapshot: encode once per tick, send to every due subscriber.

    Shapes are checked (LocalProtocolError "bad-message"); pose values are not,
    because the server only relays poses its sessions already validated. With
    ``velocities`` (n, 6) the velocity variant.
    """
    snapshot = Snapshot.from_arrays(
        tick, send_time, users, streams, capture_times, poses, velocities
    )
    return _pack(snapshot.to_wire())


def _pack(wire: dict[str, object]) -> bytes:
    data: bytes = msgpack.packb(wire)
    return data


# A tick or sequence number of 2**16 or more packs as a 5-byte uint32, the
# common case for a long session; smaller ones save up to 4 bytes a frame.
_TYPICAL_COUNTER = 1 << 16


def frame_size(
    n_poses: int, kind: Literal["update", "snapshot"] = "snapshot", *, velocities: bool = False
) -> int:
    """Exact bytes of an update or snapshot frame with ``n_poses`` poses (32-bit counter).

    ``velocities``: the velocity variant (12 bytes more a pose).
    """
    if n_poses < 0:
        raise ValueError("n_poses must be >= 0")
    header: dict[str, object]
    key = VELOCITY_POSES_KEY if velocities else POSES_KEY
    if kind == "snapshot":
        header = {"type": "snapshot", "tick": _TYPICAL_COUNTER, "time": 0.0, key: b""}
        entry = SNAPSHOT_VELOCITY_ENTRY_SIZE if velocities else SNAPSHOT_ENTRY_SIZE
    elif kind == "update":
        header = {"type": "update", "seq": _TYPICAL_COUNTER, "time": 0.0, key: b""}
        entry = UPDATE_VELOCITY_ENTRY_SIZE if velocities else UPDATE_ENTRY_SIZE
    else:
        raise ValueError(f"kind must be 'update' or 'snapshot', got {kind!r}")
    body = n_poses * entry
    # msgpack's bin header grows with the payload: bin8, bin16 or bin32.
    bin_header = 2 if body < 1 << 8 else 3 if body < 1 << 16 else 5
    return len(_pack(header)) - 2 + bin_header + body


def bytes_per_pose(
    n_poses: int = 1,
    kind: Literal["update", "snapshot"] = "snapshot",
    *,
    velocities: bool = False,
) -> float:
    """Wire bytes per pose in a frame of ``n_poses`` poses, header amortised.

    36 bytes a pose in snapshots (34 in updates; 12 more each in the velocity
    variant) plus 44-48 bytes of frame header shared by the frame's poses,
    before websocket framing (2-8 bytes a frame).
    """
    if n_poses < 1:
        raise ValueError("n_poses must be >= 1")
    return frame_size(n_poses, kind, velocities=velocities) / n_poses


def update_records(update: PoseUpdate) -> Iterator[tuple[int, float, bytes, bytes | None]]:
    """``(stream, capture time, pose bytes, velocity bytes)`` of each entry, no numpy per entry.

    The relay keeps the 28 pose bytes (and the 12 velocity bytes of the velocity
    variant; None for a plain update) as they arrived (they were validated when
    the update was received) and copies them into snapshots with
    :func:`pack_snapshot` / :func:`pack_velocity_snapshot`, so a pose crosses the
    server without being decoded.
    """
    raw = update.entries.tobytes()
    base = update.base_time
    head = _UPDATE_HEAD
    if update.has_velocities:
        size = UPDATE_VELOCITY_ENTRY_SIZE
        for off in range(0, len(raw), size):
            stream, dt = head.unpack_from(raw, off)
            start = off + head.size
            mid = start + POSE_BYTES
            yield stream, base + dt, raw[start:mid], raw[mid : mid + VELOCITY_BYTES]
        return
    for off in range(0, len(raw), UPDATE_ENTRY_SIZE):
        stream, dt = head.unpack_from(raw, off)
        start = off + head.size
        yield stream, base + dt, raw[start : start + POSE_BYTES], None


def pack_snapshot(
    tick: int, send_time: float, entries: Iterable[tuple[int, int, float, bytes]]
) -> bytes:
    """Snapshot frame bytes from ``(user, stream, capture time, pose bytes)`` entries.

    The same frame as :func:`encode_snapshot` builds from arrays, assembled from
    bytes: the relay's per-tick path. Pose bytes are not checked (they come from
    validated updates); the capture time travels as a float32 offset from
    ``send_time``.
    """
    head = _SNAPSHOT_HEAD
    parts: list[bytes] = []
    for user, stream, capture, pose in entries:
        parts.append(head.pack(user, stream, capture - send_time))
        parts.append(pose)
    return _pack({"type": Snapshot.TYPE, "tick": tick, "time": send_time, "poses": b"".join(parts)})


def pack_velocity_snapshot(
    tick: int, send_time: float, entries: Iterable[tuple[int, int, float, bytes, bytes]]
) -> bytes:
    """Velocity-variant snapshot bytes from ``(user, stream, capture, pose, velocity)`` entries.

    As :func:`pack_snapshot`, with each entry's 12 velocity bytes (6 float16,
    e.g. :data:`ZERO_VELOCITY` for a stream whose sender reports none) after its
    pose: the same frame :func:`encode_snapshot` builds with ``velocities``.
    """
    head = _SNAPSHOT_HEAD
    parts: list[bytes] = []
    for user, stream, capture, pose, velocity in entries:
        parts.append(head.pack(user, stream, capture - send_time))
        parts.append(pose)
        parts.append(velocity)
    return _pack(
        {
            "type": Snapshot.TYPE,
            "tick": tick,
            "time": send_time,
            VELOCITY_POSES_KEY: b"".join(parts),
        }
    )
