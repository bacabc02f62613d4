"""Exporting a session file: CSV or NPZ per stream, or an MCAP that Foxglove Studio opens.

:func:`export` writes every recorded stream's keyframes (capture time order):

- ``csv``: a directory with one ``user<U>_<name>.csv`` per stream, columns
  ``time, px, py, pz, qw, qx, qy, qz`` (capture time in s on the server clock;
  the pose as recorded, printed with 7 decimals for positions and 8 for
  quaternion components), plus ``streams.json`` naming each file's user and stream.
- ``npz``: one ``.npz`` with, per stream ``user<U>.<name>``, ``.time`` (K,)
  float64 capture times, ``.arrival`` (K,) float64 and ``.poses`` (K, 7) float32,
  bit-exact; ``streams`` holds the same index as JSON.
- ``foxglove``: an MCAP whose channels are JSON-encoded ``foxglove.FrameTransform``
  messages (the well-known schema, embedded as ``jsonschema``), one channel per
  user stream (topic ``/user<U>/<name>``, child frame ``user<U>/<name>``, parent
  frame ``world``), so the session plays in Foxglove Studio's 3D panel. The
  world frame is the recording's (OpenXR: +y up, +z backward).

Times and frame (:func:`export`'s ``times`` and ``z_up``): keyframe, arrival and
ownership times are the server clock as recorded (``server``; on a single relay a
monotonic clock that starts near 0, so Foxglove would show 1970), seconds since
the recording started (``relative``) or UNIX wall-clock time (``wall``, from the
start times in the recording's header). With ``z_up`` the world is turned +90 deg
about x so that +z is up (x right, +y forward: ROS and Foxglove's convention),
poses, velocities and throw velocities alike, and the frame is named
``world_z_up`` (Foxglove parent frame; ``frame`` in ``streams.json`` and the NPZ
index; ``posecast.export`` metadata of the Foxglove MCAP).

Shared objects (``recorder.objects``) are exported as streams named by the
object, not by a user: ``object_<name>.csv``, NPZ ``object.<name>.*``, Foxglove
topic ``/objects/<name>`` (child frame ``objects/<name>``), with the keyframes
as the room relayed them (the owners' and the relay's flight keyframes, times as
the room stored them). Their CSV has a ``publisher`` column (the owner who sent
the keyframe, 65535 for the relay's flight keyframes) and the velocity columns
when the relay flew the object (``nan`` for keyframes that carried none); the
NPZ has ``.publisher``. The ownership changes go beside them: ``ownership.csv``
(columns ``time, object, stream, owner, previous, reason, locked, vx, vy, vz,
wx, wy, wz``: empty for no user, ``nan`` for no throw velocity), NPZ
``ownership`` (JSON), and a Foxglove ``/objects/ownership`` channel of JSON
messages with the same fields.

:func:`csv_bytes` is the vectorised CSV writer behind these files and the
offline replay's rendered poses: numbers are printed in fixed point with numpy
integer arithmetic instead of one Python format call per value (~50x faster).
"""

from __future__ import annotations

import json
import math
import os
import re
import struct
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import zstandard
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer
from numpy.typing import NDArray

from posecast.recorder.check import EXPORT_LIBRARY_PREFIX
from posecast.recorder.compact import expand_group, is_group
from posecast.recorder.export_frame import (
    TIME_BASES,
    Y_UP_FRAME,
    Z_UP_FRAME,
    TimeBase,
    as_exported,
    export_description,
)
from posecast.recorder.format import (
    EVENTS_TOPIC,
    POSES_TOPIC,
    PRESENCE_TOPIC,
    SESSION_METADATA,
    decode_json,
    posecast_version,
    to_ns,
)
from posecast.recorder.objects import ROOM_USER, ObjectTrack, split_objects
from posecast.recorder.reader import (
    SessionReader,
    StreamData,
    UserInfo,
    decode_poses,
    split_streams,
    users_from,
)

__all__ = [
    "FRAME_TRANSFORM_SCHEMA",
    "POSE_COLUMNS",
    "TIME_BASES",
    "VELOCITY_COLUMNS",
    "Y_UP_FRAME",
    "Z_UP_FRAME",
    "ExportFormat",
    "SessionArrays",
    "TimeBase",
    "csv_bytes",
    "export",
    "read_session",
    "sorted_streams",
    "stream_label",
]

ExportFormat = Literal["csv", "npz", "foxglove"]
#: The 7 pose columns of every CSV posecast writes.
POSE_COLUMNS = ("px", "py", "pz", "qw", "qx", "qy", "qz")
#: Extra CSV columns of a stream whose updates carried velocities (world frame).
VELOCITY_COLUMNS = ("vx", "vy", "vz", "wx", "wy", "wz")
#: Decimals printed for capture times, positions and quaternion components.
_TIME_DECIMALS = 9
_POS_DECIMALS = 7
_QUAT_DECIMALS = 8

_TIME_OBJECT: dict[str, Any] = {
    "type": "object",
    "title": "time",
    "properties": {
        "sec": {"type": "integer", "minimum": 0},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999},
    },
    "description": "Timestamp of transform",
}


def _number_object(title: str, description: str, keys: str) -> dict[str, Any]:
    return {
        "title": title,
        "description": description,
        "type": "object",
        "properties": {k: {"type": "number", "description": f"{k} value"} for k in keys},
    }


#: Foxglove's well-known ``foxglove.FrameTransform`` schema, as JSON Schema.
FRAME_TRANSFORM_SCHEMA: dict[str, Any] = {
    "title": "foxglove.FrameTransform",
    "description": "A transform between two reference frames in 3D space",
    "type": "object",
    "properties": {
        "timestamp": _TIME_OBJECT,
        "parent_frame_id": {"type": "string", "description": "Name of the parent frame"},
        "child_frame_id": {"type": "string", "description": "Name of the child frame"},
        "translation": _number_object(
            "foxglove.Vector3", "Translation component of the transform", "xyz"
        ),
        "rotation": _number_object(
            "foxglove.Quaternion", "Rotation component of the transform", "xyzw"
        ),
    },
}

_UNSAFE = re.compile(r"[^A-Za-z0-9_.-]+")
_CSV_UNSAFE = re.compile(r"[,\x00-\x1f\"]+")

_OP_LEN = struct.Struct("<BQ")
_MSG_HEAD = struct.Struct("<HIQQ")  # channel, sequence, log time, publish time
_CHUNK_HEAD = struct.Struct("<QQQI")  # start, end, uncompressed size, crc
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
_MESSAGE_OP = 0x05


# -- CSV ------------------------------------------------------------------------------


def _int_digits(ip: NDArray[np.int64]) -> NDArray[np.int64]:
    """Decimal digits of non-negative integers (at least 1)."""
    nd = np.ones(ip.shape, dtype=np.int64)
    p = 10
    while p <= 10**18:
        ge = ip >= p
        if not ge.any():
            break
        nd += ge
        p *= 10
    return nd


#: The zero-padded 4 decimal digits of 0..9999, each as one little-endian uint32
#: (viewing an array of them as bytes gives the characters in order).
_DIGITS4 = np.frombuffer(b"".join(f"{k:04d}".encode() for k in range(10_000)), dtype="<u4")


def _digit_chars(v: NDArray[np.int64], width: int) -> NDArray[np.uint8]:
    """Non-negative integers as ``width`` zero-padded decimal digits: (N, width) bytes."""
    groups = -(-width // 4)
    words = np.empty((groups, v.shape[0]), dtype="<u4")
    rest = v
    for g in range(groups):  # four digits at a time, right to left
        high = rest // 10_000
        np.take(_DIGITS4, rest - high * 10_000, out=words[groups - 1 - g])
        rest = high
    chars: NDArray[np.uint8] = np.ascontiguousarray(words.T).view(np.uint8)
    return chars[:, 4 * groups - width :]


def _fixed_chars(x: NDArray[Any], decimals: int) -> NDArray[np.uint8] | None:
    """``x`` printed like ``%.{decimals}f``: an (N, W) byte matrix, NUL-padded on the left.

    None when a value cannot be printed this way (non-finite, or too large for
    int64 fixed point); the caller then falls back to Python formatting.
    """
    v = np.asarray(x, dtype=np.float64)
    n = v.shape[0]
    if n == 0:
        return np.zeros((0, 1), dtype=np.uint8)
    if not np.isfinite(v).all():
        return None
    scale = 10**decimals
    mag = np.abs(v) * scale
    if float(mag.max()) >= 2.0**62:
        return None
    fixed = np.rint(mag).astype(np.int64)
    neg = (v < 0) & (fixed > 0)  # no "-0.000"
    nd = _int_digits(fixed // scale)
    width_int = int(nd.max())
    digits = _digit_chars(fixed, width_int + decimals)
    width = 1 + width_int + (1 + decimals if decimals else 0)
    out = np.empty((n, width), dtype=np.uint8)
    out[:, 0] = 0
    out[:, 1 : 1 + width_int] = digits[:, :width_int]
    if decimals:
        out[:, width_int + 1] = ord(".")
        out[:, width_int + 2 :] = digits[:, width_int:]
    # Blank the leading zeros; put the sign just before the first digit.
    lead = width_int - nd  # leading zero columns, after the sign column
    if width_int > 1:
        blank = np.arange(width_int)[None, :] < lead[:, None]
        out[:, 1 : 1 + width_int][blank] = 0
    rows = np.nonzero(neg)[0]
    out[rows, lead[rows]] = ord("-")
    return out


def _column_chars(col: NDArray[Any], decimals: int | None) -> NDArray[np.uint8] | None:
    if col.dtype.kind == "S":
        if col.dtype.itemsize == 0:
            return np.zeros((col.shape[0], 1), dtype=np.uint8)
        return np.ascontiguousarray(col).view(np.uint8).reshape(col.shape[0], -1)
    if col.dtype.kind in "iub":
        return _fixed_chars(col.astype(np.float64), 0)
    return _fixed_chars(col, 6 if decimals is None else decimals)


def _slow_csv(columns: Sequence[NDArray[Any]], decimals: Sequence[int | None]) -> bytes:
    fmts = []
    for col, dec in zip(columns, decimals, strict=True):
        if col.dtype.kind == "S":
            fmts.append("%s")
        elif col.dtype.kind in "iub":
            fmts.append("%d")
        else:
            fmts.append(f"%.{6 if dec is None else dec}f")
    fmt = ",".join(fmts) + "\n"
    rows = zip(
        *[c.astype(str) if c.dtype.kind == "S" else c.tolist() for c in columns], strict=True
    )
    return "".join(fmt % row for row in rows).encode()


def csv_bytes(
    header: Sequence[str],
    columns: Sequence[NDArray[Any]],
    decimals: Sequence[int | None],
) -> bytes:
    """CSV text of equal-length columns: a header line, then one line per row.

    Float columns print in fixed point with ``decimals`` digits (default 6),
    integer columns as integers, byte-string (``S``) columns as they are (they
    must not contain commas or NUL). Non-finite floats print as ``nan``/``inf``.
    """
    if not (len(header) == len(columns) == len(decimals)):
        raise ValueError("expected one header and one decimals entry per column")
    cols = [np.asarray(c) for c in columns]
    n = cols[0].shape[0] if cols else 0
    if any(c.shape != (n,) for c in cols):
        raise ValueError("expected 1-d columns of equal length")
    head = (",".join(header) + "\n").encode()
    if n == 0:
        return head
    parts: list[NDArray[np.uint8]] = []
    for k, (col, dec) in enumerate(zip(cols, decimals, strict=True)):
        chars = _column_chars(col, dec)
        if chars is None:
            return head + _slow_csv(cols, decimals)
        parts.append(chars)
        sep = np.full((n, 1), ord("\n") if k == len(cols) - 1 else ord(","), dtype=np.uint8)
        parts.append(sep)
    flat = np.concatenate(parts, axis=1).ravel()
    body: bytes = flat[flat != 0].tobytes()  # drop the NUL padding
    return head + body


# -- streams ----------------------------------------------------------------------------


def stream_label(stream: StreamData) -> str:
    """``user<U>.<name>`` (or ``user<U>.stream<S>`` if unnamed), safe as a file name;
    a shared object's stream: ``object.<name>``."""
    name = stream.name or f"stream{stream.stream}"
    if stream.user == ROOM_USER and name.startswith("object:"):
        return _UNSAFE.sub("-", "object." + name.removeprefix("object:"))
    return _UNSAFE.sub("-", f"user{stream.user}.{name}")


def _frame_name(stream: StreamData) -> str:
    """Foxglove topic (after ``/``) and child frame of a stream."""
    name = stream.name or f"stream{stream.stream}"
    if stream.user == ROOM_USER and name.startswith("object:"):
        return "objects/" + name.removeprefix("object:")
    return f"user{stream.user}/{name}"


#: Columns of ``ownership.csv``.
OWNERSHIP_COLUMNS = ("time", "object", "stream", "owner", "previous", "reason", "locked")


def _ownership_csv(tracks: Sequence[ObjectTrack]) -> bytes:
    changes = sorted((c for t in tracks for c in t.changes), key=lambda c: c.time)

    def user(u: int | None) -> bytes:
        return b"" if u is None else str(u).encode()

    def vec(v: tuple[float, float, float] | None, j: int) -> float:
        return math.nan if v is None else v[j]

    cols: list[NDArray[Any]] = [
        np.array([c.time for c in changes], dtype=np.float64),
        np.array([_CSV_UNSAFE.sub("-", c.object).encode() for c in changes], dtype=bytes),
        np.array([c.stream for c in changes], dtype=np.int64),
        np.array([user(c.owner) for c in changes], dtype=bytes),
        np.array([user(c.previous) for c in changes], dtype=bytes),
        np.array([_CSV_UNSAFE.sub("-", c.reason).encode() for c in changes], dtype=bytes),
        np.array([int(c.locked) for c in changes], dtype=np.int64),
        *(np.array([vec(c.velocity, j) for c in changes], dtype=np.float64) for j in range(3)),
        *(np.array([vec(c.angular, j) for c in changes], dtype=np.float64) for j in range(3)),
    ]
    header = (*OWNERSHIP_COLUMNS, *VELOCITY_COLUMNS)
    decimals = (_TIME_DECIMALS, None, None, None, None, None, None, *(7,) * 6)
    return csv_bytes(header, cols, decimals)


@dataclass(frozen=True)
class SessionArrays:
    """A recording read whole: streams (capture-time order), users, session metadata."""

    streams: list[StreamData]
    """Ordered by (user, stream id); each stream's keyframes sorted by capture time.
    A shared object is one stream of user ``ROOM_USER`` named by the object, its
    keyframes as the room stored them (``recorder.objects``); the users' streams
    hold their own devices only."""
    users: dict[int, UserInfo]
    session: dict[str, str]
    objects: list[ObjectTrack] = field(default_factory=list)
    """The shared objects: records, ownership changes and keyframes."""


def _by_capture(s: StreamData) -> StreamData:
    order = np.argsort(s.times, kind="stable")
    return StreamData(
        user=s.user,
        stream=s.stream,
        name=s.name,
        user_name=s.user_name,
        times=s.times[order],
        arrival=s.arrival[order],
        poses=s.poses[order],
        velocities=None if s.velocities is None else s.velocities[order],
    )


def _chunk_records(buf: bytes, pos: int, dctx: zstandard.ZstdDecompressor) -> bytes | None:
    """The uncompressed records of the chunk record at ``pos``, or None if not intact."""
    b = pos + 9
    _start, _end, usize, crc = _CHUNK_HEAD.unpack_from(buf, b)
    (clen,) = _U32.unpack_from(buf, b + 28)
    compression = buf[b + 32 : b + 32 + clen].decode("ascii", "replace")
    (rlen,) = _U64.unpack_from(buf, b + 32 + clen)
    data = buf[b + 40 + clen : b + 40 + clen + rlen]
    if compression == "zstd":
        raw = dctx.decompress(data, max_output_size=usize)
    elif compression == "":
        raw = data
    else:
        return None  # lz4 and others: the reference reader handles them
    if len(raw) != usize or (crc != 0 and zlib.crc32(raw) != crc):
        return None
    return raw


def _fast_read(path: Path) -> SessionArrays | None:
    """Chunk by chunk through the summary's chunk index; None if the file is not
    a finished, intact posecast recording (the caller then uses :class:`SessionReader`).

    The indexed reader of mcap merges chunks by log time through a heap of
    Python objects (tens of microseconds a message); this reads every chunk once
    and decodes all pose messages in one vectorised pass.
    """
    with path.open("rb") as fh:
        try:
            reader = make_reader(fh, validate_crcs=True)
            summary = reader.get_summary()
            if summary is None or not summary.chunk_indexes:
                return None
            metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        except Exception:  # mcap raises many types on bad data
            return None
        topics = {cid: ch.topic for cid, ch in summary.channels.items()}
        fh.seek(0)
        buf = fh.read()
    dctx = zstandard.ZstdDecompressor()
    pose_times: list[int] = []
    pose_data: list[bytes] = []
    presence: list[tuple[int, bytes]] = []
    events: list[bytes] = []
    for index in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
        try:
            raw = _chunk_records(buf, index.chunk_start_offset, dctx)
        except Exception:  # struct, zstd: a damaged chunk
            return None
        if raw is None:
            return None
        p, end = 0, len(raw)
        while p < end:
            op, length = _OP_LEN.unpack_from(raw, p)
            if op == _MESSAGE_OP:
                channel, _seq, log_time, _pub = _MSG_HEAD.unpack_from(raw, p + 9)
                topic = topics.get(channel)
                if topic == POSES_TOPIC:
                    data = raw[p + 31 : p + 9 + length]
                    if is_group(data):
                        for t, _pub, one in expand_group(data):
                            pose_times.append(t)
                            pose_data.append(one)
                    else:
                        pose_times.append(log_time)
                        pose_data.append(data)
                elif topic == PRESENCE_TOPIC:
                    presence.append((log_time, raw[p + 31 : p + 9 + length]))
                elif topic == EVENTS_TOPIC:
                    events.append(raw[p + 31 : p + 9 + length])
            p += 9 + length
    session = metadata.get(SESSION_METADATA, {})
    users = _users(session, sorted(presence, key=lambda r: r[0]))
    # Arrival (log time) order, as SessionReader.load_streams gives it.
    order = np.argsort(np.asarray(pose_times, dtype=np.uint64), kind="stable")
    cols = decode_poses([pose_data[i] for i in order.tolist()])
    return _with_objects(split_streams(cols, users), users, session, _json_records(events))


def _json_records(datas: list[bytes]) -> list[dict[str, Any]]:
    out = []
    for data in datas:
        try:
            out.append(decode_json(data))
        except ValueError:
            continue
    return out


def _with_objects(
    pieces: dict[tuple[int, int], StreamData],
    users: dict[int, UserInfo],
    session: dict[str, str],
    events: list[dict[str, Any]],
) -> SessionArrays:
    """The users' streams and one stream per shared object, by (user, stream id)."""
    own, tracks = split_objects(events, pieces, users)
    streams = [_by_capture(own[k]) for k in sorted(own)]
    streams += [t.stream_data() for t in tracks]
    return SessionArrays(streams, users, session, tracks)


def _users(session: dict[str, str], presence: list[tuple[int, bytes]]) -> dict[int, UserInfo]:
    """What :meth:`SessionReader.users` gives, from already-read presence records."""
    decoded: list[tuple[float, dict[str, Any]]] = []
    for log_time, data in presence:
        try:
            decoded.append((log_time / 1e9, decode_json(data)))
        except ValueError:
            continue
    return users_from(session, decoded)


def read_session(path: str | os.PathLike[str]) -> SessionArrays:
    """Every stream (keyframes by capture time), the users and the session metadata.

    A finished recording is read chunk by chunk (fast); an unfinished or damaged
    one through :class:`SessionReader`, which reads what is intact.
    """
    p = Path(path)
    fast = _fast_read(p) if p.suffix == ".mcap" else None
    if fast is not None:
        return fast
    with SessionReader(p) as reader:
        found = reader.load_streams()
        users = reader.users()
        session = reader.session
        events = [e.data for e in reader.events()]
    return _with_objects(found, users, session, events)


def sorted_streams(path: str | os.PathLike[str]) -> list[StreamData]:
    """Every stream of a recording with its keyframes sorted by capture time (stable).

    Streams are ordered by (user, stream id).
    """
    return read_session(path).streams


def _index(
    streams: Sequence[StreamData],
    files: Sequence[str] | None = None,
    how: dict[str, str] | None = None,
) -> list[Any]:
    return [
        {
            "user": s.user,
            "user_name": s.user_name,
            "stream": s.stream,
            "name": s.name,
            "keyframes": len(s),
            **({} if files is None else {"file": files[i]}),
            **(how or {}),
        }
        for i, s in enumerate(streams)
    ]


def _export_csv(
    streams: Sequence[StreamData],
    out: Path,
    tracks: Sequence[ObjectTrack] = (),
    how: dict[str, str] | None = None,
) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    files = []
    header = ("time", *POSE_COLUMNS)
    decimals = (_TIME_DECIMALS, *(_POS_DECIMALS,) * 3, *(_QUAT_DECIMALS,) * 4)
    publishers = _publishers(tracks)
    for s in streams:
        name = stream_label(s).replace(".", "_", 1) + ".csv"
        poses = s.poses.astype(np.float64)
        cols = [s.times, *(poses[:, j] for j in range(7))]
        names: tuple[str, ...] = header
        digits: tuple[int, ...] = decimals
        publisher = publishers.get((s.user, s.stream, s.name))
        if publisher is not None:
            cols.append(publisher.astype(np.int64))
            names, digits = (*names, "publisher"), (*digits, 0)
        if s.velocities is not None:
            # 7 decimals: float16 velocities to within 5e-8 m/s (rad/s)
            vel = s.velocities.astype(np.float64)
            cols += [vel[:, j] for j in range(6)]
            names, digits = (*names, *VELOCITY_COLUMNS), (*digits, *(7,) * 6)
        (out / name).write_bytes(csv_bytes(names, cols, digits))
        files.append(name)
    (out / "streams.json").write_text(json.dumps(_index(streams, files, how), indent=1) + "\n")
    if tracks:
        (out / "ownership.csv").write_bytes(_ownership_csv(tracks))
    return out


def _publishers(
    tracks: Sequence[ObjectTrack],
) -> dict[tuple[int, int, str | None], NDArray[np.uint16]]:
    """(ROOM_USER, stream, name) -> who published each keyframe of that object."""
    return {(ROOM_USER, t.stream, t.name): t.publisher for t in tracks}


def _ownership_json(tracks: Sequence[ObjectTrack]) -> list[dict[str, Any]]:
    return sorted((c.as_dict() for t in tracks for c in t.changes), key=lambda c: c["time"])


def _export_npz(
    streams: Sequence[StreamData],
    out: Path,
    tracks: Sequence[ObjectTrack] = (),
    how: dict[str, str] | None = None,
) -> Path:
    if out.suffix != ".npz":
        out = out.with_name(out.name + ".npz")
    out.parent.mkdir(parents=True, exist_ok=True)
    arrays: dict[str, NDArray[Any]] = {}
    publishers = _publishers(tracks)
    for s in streams:
        label = stream_label(s)
        arrays[f"{label}.time"] = s.times
        arrays[f"{label}.arrival"] = s.arrival
        arrays[f"{label}.poses"] = s.poses
        if s.velocities is not None:
            arrays[f"{label}.velocities"] = s.velocities
        publisher = publishers.get((s.user, s.stream, s.name))
        if publisher is not None:
            arrays[f"{label}.publisher"] = publisher
    arrays["streams"] = np.array(json.dumps(_index(streams, None, how)))
    if tracks:
        arrays["ownership"] = np.array(json.dumps(_ownership_json(tracks)))
    with out.open("wb") as fh:
        np.savez(fh, **arrays)  # type: ignore[arg-type]
    return out


def _transform_message(
    t: float, child: str, pose: NDArray[np.float32], parent: str = Y_UP_FRAME
) -> bytes:
    ns = to_ns(t)
    px, py, pz, qw, qx, qy, qz = pose.tolist()
    msg = {
        "timestamp": {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000},
        "parent_frame_id": parent,
        "child_frame_id": child,
        "translation": {"x": px, "y": py, "z": pz},
        "rotation": {"x": qx, "y": qy, "z": qz, "w": qw},
    }
    return json.dumps(msg, separators=(",", ":")).encode()


def _export_foxglove(
    streams: Sequence[StreamData],
    out: Path,
    session: dict[str, str],
    tracks: Sequence[ObjectTrack] = (),
    how: dict[str, str] | None = None,
) -> Path:
    parent = (how or {}).get("frame", Y_UP_FRAME)
    if out.suffix != ".mcap":
        out = out.with_name(out.name + ".mcap")
    out.parent.mkdir(parents=True, exist_ok=True)
    # Every keyframe, across streams, in capture-time order (the Foxglove timeline).
    chan = np.concatenate(
        [np.full(len(s), i, dtype=np.int64) for i, s in enumerate(streams)]
        or [np.zeros(0, np.int64)]
    )
    row = np.concatenate(
        [np.arange(len(s), dtype=np.int64) for s in streams] or [np.zeros(0, np.int64)]
    )
    times = np.concatenate([s.times for s in streams] or [np.zeros(0)])
    order = np.argsort(times, kind="stable")
    with out.open("wb") as fh:
        writer = Writer(fh, compression=CompressionType.ZSTD)
        writer.start(profile="", library=f"{EXPORT_LIBRARY_PREFIX}{posecast_version()}")
        if session:
            writer.add_metadata("posecast.session", session)
        if how:
            writer.add_metadata("posecast.export", how)
        schema_id = writer.register_schema(
            "foxglove.FrameTransform",
            "jsonschema",
            json.dumps(FRAME_TRANSFORM_SCHEMA, separators=(",", ":")).encode(),
        )
        channel_ids = []
        children = []
        for s in streams:
            name = s.name or f"stream{s.stream}"
            children.append(_frame_name(s))
            channel_ids.append(
                writer.register_channel(
                    f"/{_frame_name(s)}",
                    "json",
                    schema_id,
                    {"user": str(s.user), "stream": str(s.stream), "name": name},
                )
            )
        for seq, k in enumerate(order.tolist()):
            i, j = int(chan[k]), int(row[k])
            s = streams[i]
            t = float(s.times[j])
            ns = to_ns(t)
            writer.add_message(
                channel_ids[i], ns, _transform_message(t, children[i], s.poses[j], parent), ns, seq
            )
        if tracks:
            _ownership_channel(writer, tracks, len(order))
        writer.finish()  # type: ignore[no-untyped-call]
    return out


def _ownership_channel(writer: Writer, tracks: Sequence[ObjectTrack], seq: int) -> None:
    """The ownership changes as JSON messages on ``/objects/ownership``."""
    schema = {
        "title": "posecast.OwnerChange",
        "type": "object",
        "properties": {
            k: {"type": ["number", "string", "boolean", "array", "null"]}
            for k in (*OWNERSHIP_COLUMNS, "velocity", "angular")
        },
    }
    schema_id = writer.register_schema(
        "posecast.OwnerChange", "jsonschema", json.dumps(schema).encode()
    )
    channel = writer.register_channel("/objects/ownership", "json", schema_id)
    for k, change in enumerate(_ownership_json(tracks)):
        ns = to_ns(change["time"])
        writer.add_message(channel, ns, json.dumps(change).encode(), ns, seq + k)


def export(
    path: str | os.PathLike[str],
    to: ExportFormat,
    out: str | os.PathLike[str],
    *,
    times: TimeBase = "server",
    z_up: bool = False,
) -> Path:
    """Export every stream of the recording at ``path``; returns what was written.

    ``to="csv"`` writes a directory ``out`` (one CSV per stream and
    ``streams.json``); ``"npz"`` one ``.npz`` file; ``"foxglove"`` one ``.mcap``
    file (the suffix is added to ``out`` if missing). ``times``: ``server``
    (as recorded), ``relative`` or ``wall``; ``z_up``: turn the world z-up (see
    the module docstring). The files say which time base and frame they use.
    """
    if to not in ("csv", "npz", "foxglove"):
        raise ValueError(f"unknown export format {to!r}; expected csv, npz or foxglove")
    if times not in TIME_BASES:
        raise ValueError(f"unknown time base {times!r}; expected {', '.join(TIME_BASES)}")
    raw = read_session(path)
    data = as_exported(raw, times, z_up)
    how = export_description(times, z_up, raw.session)
    target = Path(out)
    if to == "csv":
        return _export_csv(data.streams, target, data.objects, how)
    if to == "npz":
        return _export_npz(data.streams, target, data.objects, how)
    return _export_foxglove(data.streams, target, data.session, data.objects, how)
