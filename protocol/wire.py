"""Frame codec: one websocket message <-> one ``Message``, without session rules.

Every frame is one msgpack map with a string "type". ``decode_message`` checks
size, msgpack syntax, type and schema, and raises ``RemoteProtocolError`` with
the code for the first problem; it knows nothing of state, limits beyond the
frame size, or stream ownership (that is ``protocol.session``). The recorder
can use these two functions to store and read raw frames.
"""

from __future__ import annotations

from collections.abc import Callable

import msgpack
import numpy as np

from posecast.protocol._validate import U63_MAX, check_float, check_int
from posecast.protocol.errors import ErrorCode, ProtocolViolation, RemoteProtocolError
from posecast.protocol.events import Message
from posecast.protocol.limits import MAX_FRAME_SIZE, PROTOCOL_VERSION
from posecast.protocol.messages import (
    Bye,
    ControlMessage,
    ErrorMessage,
    Hello,
    Join,
    Joined,
    PeerJoined,
    PeerLeft,
    PeerResumed,
    PeerStalled,
    Ping,
    Pong,
    RateNotice,
    Renew,
    SetRate,
    UserEvent,
    Welcome,
)
from posecast.protocol.objects import OBJECT_MESSAGE_TYPES
from posecast.protocol.poses import (
    POSES_KEY,
    SNAPSHOT_DTYPE,
    SNAPSHOT_VELOCITY_DTYPE,
    UPDATE_DTYPE,
    UPDATE_VELOCITY_DTYPE,
    VELOCITY_POSES_KEY,
    PoseUpdate,
    Snapshot,
)

__all__ = ["MESSAGE_TYPES", "decode_message", "encode_message"]

_CONTROL: dict[str, type[ControlMessage]] = {
    cls.TYPE: cls
    for cls in (
        Hello,
        Welcome,
        Join,
        Joined,
        PeerJoined,
        PeerLeft,
        PeerStalled,
        PeerResumed,
        Ping,
        Pong,
        SetRate,
        RateNotice,
        Renew,
        UserEvent,
        ErrorMessage,
        Bye,
    )
}
_CONTROL.update({cls.TYPE: cls for cls in OBJECT_MESSAGE_TYPES})

MESSAGE_TYPES = frozenset([*_CONTROL, PoseUpdate.TYPE, Snapshot.TYPE])
"""Every "type" this protocol version knows."""

# Per type: (plain keys, velocity-variant keys). The records' key says which layout.
_POSE_KEYS = {
    "update": (
        frozenset({"type", "seq", "time", POSES_KEY}),
        frozenset({"type", "seq", "time", VELOCITY_POSES_KEY}),
    ),
    "snapshot": (
        frozenset({"type", "tick", "time", POSES_KEY}),
        frozenset({"type", "tick", "time", VELOCITY_POSES_KEY}),
    ),
}
_DTYPES = {
    ("update", False): UPDATE_DTYPE,
    ("update", True): UPDATE_VELOCITY_DTYPE,
    ("snapshot", False): SNAPSHOT_DTYPE,
    ("snapshot", True): SNAPSHOT_VELOCITY_DTYPE,
}


def encode_message(message: Message) -> bytes:
    """The frame bytes of ``message`` (no state or limit checks; sessions add those)."""
    data: bytes = msgpack.packb(message.to_wire())
    return data


def _unpack(data: bytes | bytearray | memoryview) -> dict[str, object]:
    try:
        # use_list=False: arrays arrive as tuples, as the frozen messages want.
        # Size limits inside msgpack default to len(data), so a short frame
        # cannot announce a huge array.
        wire = msgpack.unpackb(data, raw=False, use_list=False)
    except msgpack.ExtraData:
        raise RemoteProtocolError(ErrorCode.BAD_FRAME, "trailing bytes after frame") from None
    except Exception:
        # msgpack documents ValueError, FormatError and StackError and warns
        # that "other exceptions can be raised": any failure here is garbage in.
        raise RemoteProtocolError(ErrorCode.BAD_FRAME, "not a msgpack frame") from None
    if not isinstance(wire, dict):
        raise RemoteProtocolError(ErrorCode.BAD_FRAME, "frame is not a map")
    return wire


def _pose_frame(wire: dict[str, object], type_: str) -> PoseUpdate | Snapshot:
    plain, with_velocity = _POSE_KEYS[type_]
    keys = wire.keys()
    if keys == plain:
        key, velocity = POSES_KEY, False
    elif keys == with_velocity:
        key, velocity = VELOCITY_POSES_KEY, True
    else:
        fields = ", ".join(sorted(plain - {"type", POSES_KEY}))
        raise RemoteProtocolError(
            ErrorCode.BAD_MESSAGE,
            f"{type_} needs exactly {fields} and {POSES_KEY} (or {VELOCITY_POSES_KEY})",
        )
    body = wire[key]
    if type(body) is not bytes:
        raise RemoteProtocolError(ErrorCode.BAD_MESSAGE, f"{type_}.{key} must be bin")
    dtype = _DTYPES[type_, velocity]
    if len(body) % dtype.itemsize:
        raise RemoteProtocolError(
            ErrorCode.BAD_MESSAGE, f"{type_}.{key} is not whole {dtype.itemsize}-byte records"
        )
    time = check_float(f"{type_}.time", wire["time"])
    entries = np.frombuffer(body, dtype=dtype)
    if type_ == "update":
        return PoseUpdate._trusted(check_int("update.seq", wire["seq"], 0, U63_MAX), time, entries)
    return Snapshot._trusted(check_int("snapshot.tick", wire["tick"], 0, U63_MAX), time, entries)


def _check_version(wire: dict[str, object], type_: str) -> None:
    # Checked before the schema: a peer of another version may also have other
    # fields, and "version-mismatch" is the error that tells it what is wrong.
    version = wire.get("version", PROTOCOL_VERSION)
    if version != PROTOCOL_VERSION or type(version) is not int:
        raise RemoteProtocolError(
            ErrorCode.VERSION_MISMATCH,
            f"{type_} for version {str(version)[:16]}, this is {PROTOCOL_VERSION}",
        )


_DECODERS: dict[str, Callable[[dict[str, object]], Message]] = {
    name: cls.from_wire  # type: ignore[misc]
    for name, cls in _CONTROL.items()
}


def decode_message(
    data: bytes | bytearray | memoryview | str, *, max_frame_size: int = MAX_FRAME_SIZE
) -> Message:
    """Decode one frame; raise ``RemoteProtocolError`` if it is not a valid message.

    A ``str`` (what websocket libraries return for a text frame) is accepted and
    refused as a bad-frame, so the caller need not special-case text frames.
    """
    if isinstance(data, str):
        raise RemoteProtocolError(ErrorCode.BAD_FRAME, "text frame, posecast frames are binary")
    if len(data) > max_frame_size:
        raise RemoteProtocolError(
            ErrorCode.FRAME_TOO_LARGE, f"frame of {len(data)} bytes over {max_frame_size}"
        )
    wire = _unpack(data)
    type_ = wire.get("type")
    if type(type_) is not str:
        raise RemoteProtocolError(ErrorCode.BAD_FRAME, "frame has no string type")
    if type_ not in MESSAGE_TYPES:
        raise RemoteProtocolError(ErrorCode.UNKNOWN_TYPE, f"unknown type {type_[:32]!r}")
    try:
        if type_ == "update" or type_ == "snapshot":
            return _pose_frame(wire, type_)
        if type_ == "hello" or type_ == "welcome":
            _check_version(wire, type_)
        return _DECODERS[type_](wire)
    except ProtocolViolation as exc:
        # Constructors raise LocalProtocolError, speaking for this side; here
        # the fault is the peer's. Either way, record which message it was.
        raise RemoteProtocolError(exc.code, exc.message, in_reply_to=type_) from None
