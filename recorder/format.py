"""What a posecast session file contains: channels, schemas and the pose message layout.

A session file is an MCAP file (profile ``posecast``) with four channels, always
registered in this order (so their ids are 1-4 in every file the recorder writes):

=========  ==================  =====================================================
topic      message encoding    one message per
=========  ==================  =====================================================
poses      ``posecast.pose.v1``  client pose update the server accepted (below)
events     ``json``            reliable event (grab, release, button, scene step, ...;
                               shared objects: ``object_create``, ``owner``,
                               ``object_remove``, see ``recorder.objects``)
presence   ``json``            join / leave / rate change of a user
drops      ``json``            drop or skip on the server, or records the recorder lost
=========  ==================  =====================================================

The relay's keyframes of a thrown shared object in flight are pose messages of
user 65535 (``ROOM_USER``); an owner's updates carry the object's stream among its
own (``recorder.objects``, ``docs/reference/recording-format.md``).

Every message's ``log_time`` is its arrival time on the server clock in
nanoseconds; ``publish_time`` is the (newest) capture time in nanoseconds, and the
arrival time for JSON records. ``sequence`` counts every record of the file, over
all channels, from 0: a gap in it is a lost record. JSON channels carry a
``jsonschema`` schema so that other tools (Foxglove, ``mcap cat``) can read them.

Pose message layout (little-endian, packed, ``22 + 38 n`` bytes for n streams)::

    offset      type        field
    0           u8          layout version (1)
    1           u8          flags (bit 0: velocities follow the poses)
    2           u16         user id
    4           u16         n: number of streams in this update
    6           u64         update sequence number (the client's ``seq``)
    14          f64         arrival time, s, server clock
    22          u16[n]      stream ids
    22 + 2n     u64[n]      capture time bits XOR arrival time bits
    22 + 10n    u8[4][7n]   the (n, 7) float32 poses, byte-shuffled
    22 + 38n    f16[n][6]   only with flags bit 0: the velocities the update
                            carried (linear m/s, angular rad/s, world frame;
                            the protocol's velocity variant), 12 B a stream

Both transforms are exact and exist only to help the chunk compressor: a capture
time shares its sign, exponent and high mantissa bits with the arrival time, so
the XOR leaves mostly zero bytes; the poses ``[px, py, pz, qw, qx, qy, qz]`` are
stored as four byte planes (plane b holds byte b of each of the 7n float32
values, in row-major order), which groups the slowly varying sign and exponent
bytes together. Decoding gives back the float64 capture times and the float32
poses bit for bit (NaN payloads included).

Layout 2 (:mod:`recorder.compact`): the updates of a compact session (the
client sent codec codes; the relay relays their dequantised float32) are
recorded as those codes, a group of updates in one message (first byte 2),
delta-coded stream by stream inside the message, with the room volume, so that
every message decodes on its own. Its log time is its first update's arrival,
its publish time its last update's; readers expand it into the layout 1
messages of its updates (the same bytes :func:`encode_pose` makes of them), so
everything that reads layout 1 reads layout 2 files, bit for bit. Raw sessions
are recorded in layout 1, unchanged. The first byte of a ``poses`` message
tells its layout. The writer writes a group just before its chunk closes (every
0.5 s), so a group never spans two chunks; it takes one ``sequence`` number.

Session metadata lives in MCAP metadata records: ``posecast.session`` (written at
open: room, posecast version, start time on both clocks, the users present at
the start as JSON, recorder settings) and ``posecast.session.end`` (written on a
clean close).
"""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Mapping
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from posecast.protocol.errors import PosecastError

__all__ = [
    "CHANNELS",
    "DROPS_TOPIC",
    "EVENTS_TOPIC",
    "FORMAT_VERSION",
    "POSES_TOPIC",
    "POSE_ENCODING",
    "POSE_HEADER_SIZE",
    "POSE_STREAM_SIZE",
    "PRESENCE_TOPIC",
    "PROFILE",
    "QUEUE_OVERFLOW_KIND",
    "SESSION_END_METADATA",
    "SESSION_METADATA",
    "VELOCITY_FLAG",
    "VELOCITY_SIZE",
    "ChannelSpec",
    "FormatError",
    "PoseRecord",
    "decode_json",
    "decode_pose",
    "encode_json",
    "encode_pose",
    "encode_pose_batch",
    "pose_message_size",
    "posecast_version",
    "seconds",
    "to_ns",
]

PROFILE = "posecast"
FORMAT_VERSION = 1
POSE_ENCODING = "posecast.pose.v1"
POSES_TOPIC = "poses"
EVENTS_TOPIC = "events"
PRESENCE_TOPIC = "presence"
DROPS_TOPIC = "drops"
SESSION_METADATA = "posecast.session"
SESSION_END_METADATA = "posecast.session.end"
#: ``kind`` of the drops record the recorder writes for records its queue lost.
QUEUE_OVERFLOW_KIND = "recorder-queue-overflow"

_HEAD = struct.Struct("<BBHHQd")
POSE_HEADER_SIZE = _HEAD.size
#: Bytes per stream in a pose message: id u16, capture time u64, pose 7 x f32.
POSE_STREAM_SIZE = 2 + 8 + 28
#: Flags bit of a pose message that carries velocities, and their bytes per stream.
VELOCITY_FLAG = 1
VELOCITY_SIZE = 12
_F64 = struct.Struct("<d")
_U16 = np.dtype("<u2")
_U16_MAX = 0xFFFF
_U64_MAX = (1 << 64) - 1


class FormatError(PosecastError, ValueError):
    """Bytes that are not a valid posecast record, with the reason."""


@dataclass(frozen=True)
class ChannelSpec:
    """One channel of a session file and its schema, as the recorder registers it."""

    topic: str
    message_encoding: str
    schema_name: str
    schema_encoding: str
    schema_data: bytes


def _json_schema(title: str, required: tuple[str, ...], props: Mapping[str, Any]) -> bytes:
    schema = {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": title,
        "type": "object",
        "properties": dict(props),
        "required": list(required),
    }
    return json.dumps(schema, separators=(",", ":")).encode()


_POSE_LAYOUT = (
    b"posecast pose update, little-endian, packed: u8 version=1, u8 flags=0, u16 user, "
    b"u16 n, u64 seq, f64 arrival_s; u16[n] stream; u64[n] capture_bits^arrival_bits; "
    b"u8[4][7n] byte planes of float32 poses (n,7) [px,py,pz,qw,qx,qy,qz], row-major; "
    b"if flags bit 0: float16 velocities (n,6) [vx,vy,vz,wx,wy,wz] (world frame)"
)
_NUM = {"type": "number"}
_INT = {"type": "integer"}
_STR = {"type": "string"}

#: The channels of a session file in registration order (channel id = index + 1).
CHANNELS: tuple[ChannelSpec, ...] = (
    ChannelSpec(POSES_TOPIC, POSE_ENCODING, "posecast.PoseUpdate", "posecast.layout", _POSE_LAYOUT),
    ChannelSpec(
        EVENTS_TOPIC,
        "json",
        "posecast.Event",
        "jsonschema",
        _json_schema("posecast event", ("kind",), {"kind": _STR, "time": _NUM, "user": _INT}),
    ),
    ChannelSpec(
        PRESENCE_TOPIC,
        "json",
        "posecast.Presence",
        "jsonschema",
        _json_schema(
            "posecast presence (join, leave, rate)",
            ("kind", "user"),
            {
                "kind": {"enum": ["join", "leave", "rate"]},
                "user": _INT,
                "time": _NUM,
                "name": _STR,
                "label": {"type": ["string", "null"]},
                "streams": {"type": "object", "additionalProperties": _INT},
                "rate": _NUM,
                "reason": _STR,
            },
        ),
    ),
    ChannelSpec(
        DROPS_TOPIC,
        "json",
        "posecast.Drop",
        "jsonschema",
        _json_schema(
            "posecast drop or skip",
            ("kind",),
            {"kind": _STR, "time": _NUM, "user": _INT, "count": _INT},
        ),
    ),
)


@dataclass(frozen=True, eq=False)
class PoseRecord:
    """One recorded pose update: arrays are read-only, poses ``(n, 7)`` float32."""

    user: int
    seq: int
    arrival: float
    streams: NDArray[np.uint16]
    capture_times: NDArray[np.float64]
    poses: NDArray[np.float32]
    #: ``(n, 6)`` float16 velocities if the update carried them (velocity variant).
    velocities: NDArray[np.float16] | None = None

    def __len__(self) -> int:
        return len(self.streams)


def posecast_version() -> str:
    """The installed posecast version, or ``"unknown"``."""
    try:
        return version("posecast")
    except PackageNotFoundError:
        return "unknown"


def to_ns(t: float) -> int:
    """Seconds to MCAP nanoseconds (u64): rounded, clamped at 0 and 2**64 - 1."""
    if 0.0 <= t < 1e10:  # the usual case (NaN fails the test)
        return int(t * 1e9 + 0.5)
    if not math.isfinite(t):
        return 0 if t < 0 or math.isnan(t) else _U64_MAX
    ns = round(t * 1e9)
    return 0 if ns < 0 else min(ns, _U64_MAX)


def to_ns_many(t: NDArray[np.float64]) -> list[int]:
    """:func:`to_ns` of every element, computed in one numpy pass where it can be."""
    if len(t) and bool(np.all((t >= 0.0) & (t < 1e10))):
        # the same float64 operations as to_ns, then truncation (the values are positive)
        return (t * 1e9 + 0.5).astype(np.int64).tolist()  # type: ignore[no-any-return]
    return [to_ns(x) for x in t.tolist()]


def seconds(ns: int) -> float:
    """MCAP nanoseconds to seconds."""
    return ns / 1e9


def pose_message_size(n: int, velocities: bool = False) -> int:
    """Bytes of a pose message with ``n`` streams (with velocities: 12 more each)."""
    return POSE_HEADER_SIZE + (POSE_STREAM_SIZE + (VELOCITY_SIZE if velocities else 0)) * n


def _xor_times(data: bytes, arrival: float) -> bytes:
    # XOR every 8-byte word of ``data`` with the bits of ``arrival``: one big-int
    # operation, several times faster than numpy on a few values.
    n = len(data)
    mask = int.from_bytes(_F64.pack(arrival) * (n >> 3), "little")
    return (int.from_bytes(data, "little") ^ mask).to_bytes(n, "little")


def encode_pose(
    user: int,
    seq: int,
    arrival: float,
    streams: ArrayLike,
    capture_times: ArrayLike,
    poses: ArrayLike,
    velocities: ArrayLike | None = None,
) -> bytes:
    """Pack one update: stream ids (n,), capture times (n,) s, poses (n, 7) as float32.

    Float64 poses are rounded to float32 (what the wire carries anyway).
    ``velocities`` (n, 6), if the update carried them, are stored as float16 (the
    wire's type: float16 values round-trip exactly).
    """
    if not 0 <= user <= _U16_MAX:
        raise FormatError(f"user id {user} is not a u16")
    if not 0 <= seq <= _U64_MAX:
        raise FormatError(f"sequence number {seq} is not a u64")
    s = np.asarray(streams)
    c = np.asarray(capture_times, dtype="<f8")
    p = np.asarray(poses, dtype="<f4")
    n = s.shape[0] if s.ndim == 1 else -1
    if n < 0 or n > _U16_MAX or c.shape != (n,) or p.shape != (n, 7):
        raise FormatError(
            f"shapes must be streams (n,), capture_times (n,), poses (n, 7); got "
            f"{s.shape}, {c.shape}, {p.shape}"
        )
    if s.dtype != _U16:
        if n and (not np.issubdtype(s.dtype, np.integer) or s.min() < 0 or s.max() > _U16_MAX):
            raise FormatError("stream ids must be integers in 0..65535")
        s = s.astype(_U16)
    tail = b""
    if velocities is not None:
        v = np.asarray(velocities)
        if v.shape != (n, 6):
            raise FormatError(f"velocities must have shape ({n}, 6), got {v.shape}")
        tail = v.astype("<f2").tobytes()
    arrival = float(arrival)
    raw = p.tobytes()
    return b"".join(
        (
            _HEAD.pack(
                FORMAT_VERSION, 0 if velocities is None else VELOCITY_FLAG, user, n, seq, arrival
            ),
            s.tobytes(),
            _xor_times(c.tobytes(), arrival),
            raw[0::4],
            raw[1::4],
            raw[2::4],
            raw[3::4],
            tail,
        )
    )


_HEAD_DTYPE = np.dtype(
    [
        ("version", "u1"),
        ("flags", "u1"),
        ("user", "<u2"),
        ("n", "<u2"),
        ("seq", "<u8"),
        ("arrival", "<f8"),
    ]
)


def encode_pose_batch(
    users: ArrayLike,
    seqs: ArrayLike,
    arrivals: ArrayLike,
    streams: ArrayLike,
    capture_times: ArrayLike,
    poses: ArrayLike,
    velocities: ArrayLike | None = None,
) -> list[bytes]:
    """:func:`encode_pose` for ``m`` updates of ``n`` streams each, in a few numpy passes.

    ``users``, ``seqs``, ``arrivals`` ``(m,)``; ``streams``, ``capture_times``
    ``(m, n)``; ``poses`` ``(m, n, 7)``; ``velocities`` ``(m, n, 6)`` or ``None``.
    Returns the ``m`` messages, each byte for byte what :func:`encode_pose` makes.
    """
    p = np.ascontiguousarray(poses, dtype="<f4")
    if p.ndim != 3 or p.shape[2] != 7:
        raise FormatError(f"poses must have shape (m, n, 7), got {p.shape}")
    m, n = p.shape[:2]
    u = np.asarray(users)
    q = np.asarray(seqs)
    a = np.ascontiguousarray(arrivals, dtype="<f8")
    s = np.asarray(streams)
    c = np.ascontiguousarray(capture_times, dtype="<f8")
    if u.shape != (m,) or q.shape != (m,) or a.shape != (m,) or s.shape != (m, n):
        raise FormatError("users, seqs, arrivals must be (m,) and streams (m, n)")
    if c.shape != (m, n) or n > _U16_MAX:
        raise FormatError("capture_times must be (m, n), n at most 65535")
    if m and (u.min() < 0 or u.max() > _U16_MAX or q.min() < 0):
        raise FormatError("user ids must be u16, sequence numbers u64")
    if s.size and (s.min() < 0 or s.max() > _U16_MAX):
        raise FormatError("stream ids must be integers in 0..65535")
    v = None if velocities is None else np.asarray(velocities).astype("<f2")
    if v is not None and v.shape != (m, n, 6):
        raise FormatError(f"velocities must have shape ({m}, {n}, 6), got {v.shape}")
    head = np.empty(m, _HEAD_DTYPE)
    head["version"] = FORMAT_VERSION
    head["flags"] = 0 if v is None else VELOCITY_FLAG
    head["user"] = u
    head["n"] = n
    head["seq"] = q
    head["arrival"] = a
    parts = [
        head.view(np.uint8).reshape(m, _HEAD.size),
        np.ascontiguousarray(s, dtype="<u2").view(np.uint8).reshape(m, 2 * n),
        (c.view("<u8") ^ a.view("<u8")[:, None]).view(np.uint8).reshape(m, 8 * n),
        # byte plane b holds byte b of every float32, in row-major order
        p.view(np.uint8).reshape(m, 7 * n, 4).transpose(0, 2, 1).reshape(m, 28 * n),
    ]
    if v is not None:
        parts.append(v.view(np.uint8).reshape(m, 12 * n))
    blob = np.concatenate(parts, axis=1).tobytes()
    size = pose_message_size(n, v is not None)
    return [blob[i * size : (i + 1) * size] for i in range(m)]


def decode_pose(data: bytes | bytearray | memoryview) -> PoseRecord:
    """Unpack a pose message written by :func:`encode_pose` (bit-exact)."""
    data = bytes(data)
    if len(data) < POSE_HEADER_SIZE:
        raise FormatError(f"pose message of {len(data)} bytes is shorter than its header")
    ver, flags, user, n, seq, arrival = _HEAD.unpack_from(data, 0)
    if ver == 2:
        raise FormatError("a layout 2 (compact) pose message: decode it with recorder.compact")
    if ver != FORMAT_VERSION:
        raise FormatError(f"unknown pose layout version {ver}")
    if flags & ~VELOCITY_FLAG:
        raise FormatError(f"unknown pose message flags {flags:#04x}")
    has_v = bool(flags & VELOCITY_FLAG)
    if len(data) != pose_message_size(n, has_v):
        raise FormatError(
            f"pose message of {len(data)} bytes, expected {pose_message_size(n, has_v)}"
        )
    off = POSE_HEADER_SIZE
    streams = np.frombuffer(data, _U16, n, off)
    off += 2 * n
    caps = np.frombuffer(_xor_times(data[off : off + 8 * n], arrival), "<f8")
    off += 8 * n
    k = 7 * n
    raw = bytearray(4 * k)
    for b in range(4):
        raw[b::4] = data[off + b * k : off + (b + 1) * k]
    poses = np.frombuffer(raw, "<f4").reshape(n, 7)
    poses.flags.writeable = False
    velocities = None
    if has_v:
        velocities = np.frombuffer(data, "<f2", 6 * n, off + 4 * k).reshape(n, 6)
    return PoseRecord(user, seq, arrival, streams, caps, poses, velocities)


def _json_default(obj: object) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, bytes | bytearray | memoryview):
        return bytes(obj).hex()
    if isinstance(obj, set | frozenset | tuple):
        return list(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def encode_json(record: Mapping[str, Any]) -> bytes:
    """Compact UTF-8 JSON; numpy values become numbers or lists, bytes become hex."""
    return json.dumps(
        dict(record), separators=(",", ":"), default=_json_default, ensure_ascii=False
    ).encode()


def decode_json(data: bytes | bytearray | memoryview) -> dict[str, Any]:
    """A JSON record back as a dict."""
    try:
        value = json.loads(bytes(data))
    except ValueError as exc:
        raise FormatError(f"not a JSON record: {exc}") from exc
    if not isinstance(value, dict):
        raise FormatError("a JSON record must be an object")
    return value
