"""posecast wire protocol, sans-I/O: bytes in, events out; no sockets, clocks or asyncio.

A connection end is a ``ClientSession`` or ``ServerSession``: feed each received
websocket message to ``receive_data`` and act on the events it returns; call
``send`` and write the bytes it returns. Snapshots are encoded once per tick
with ``encode_snapshot``, outside any session. Errors are listed in
``protocol.errors``, the session rules in ``protocol._state``, the pose frame
layout in ``protocol.poses``.
"""

from protocol._state import Role, State
from protocol.errors import (
    MAX_CLOSE_REASON_BYTES,
    ErrorCode,
    LocalProtocolError,
    ProtocolViolation,
    RemoteProtocolError,
    close_reason,
)
from protocol.events import Event, Message, ProtocolError
from protocol.limits import (
    DEFAULT_LIMITS,
    MAX_EVENT_PAYLOAD,
    MAX_FRAME_SIZE,
    MAX_PAYLOAD_DEPTH,
    MAX_RATE,
    MAX_STREAM_NAME_LENGTH,
    MAX_STREAMS_PER_USER,
    MAX_TEXT_LENGTH,
    MIN_RATE,
    PROTOCOL_VERSION,
    QUAT_NORM_TOLERANCE,
    Limits,
)
from protocol.messages import (
    DEVICE_NAMES,
    EVENT_KINDS,
    OBJECT_PREFIX,
    Bye,
    ControlMessage,
    ErrorMessage,
    Hello,
    Join,
    Joined,
    PeerJoined,
    PeerLeft,
    Ping,
    Pong,
    SetRate,
    UserEvent,
    Welcome,
    is_valid_stream_name,
)
from protocol.poses import (
    SNAPSHOT_DTYPE,
    SNAPSHOT_ENTRY_SIZE,
    UPDATE_DTYPE,
    UPDATE_ENTRY_SIZE,
    PoseUpdate,
    Snapshot,
    bytes_per_pose,
    encode_snapshot,
    encode_update,
    frame_size,
    pose_problem,
)
from protocol.session import ClientSession, ServerSession, SessionStatistics
from protocol.wire import MESSAGE_TYPES, decode_message, encode_message

__all__ = [
    "DEFAULT_LIMITS",
    "DEVICE_NAMES",
    "EVENT_KINDS",
    "MAX_CLOSE_REASON_BYTES",
    "MAX_EVENT_PAYLOAD",
    "MAX_FRAME_SIZE",
    "MAX_PAYLOAD_DEPTH",
    "MAX_RATE",
    "MAX_STREAMS_PER_USER",
    "MAX_STREAM_NAME_LENGTH",
    "MAX_TEXT_LENGTH",
    "MESSAGE_TYPES",
    "MIN_RATE",
    "OBJECT_PREFIX",
    "PROTOCOL_VERSION",
    "QUAT_NORM_TOLERANCE",
    "SNAPSHOT_DTYPE",
    "SNAPSHOT_ENTRY_SIZE",
    "UPDATE_DTYPE",
    "UPDATE_ENTRY_SIZE",
    "Bye",
    "ClientSession",
    "ControlMessage",
    "ErrorCode",
    "ErrorMessage",
    "Event",
    "Hello",
    "Join",
    "Joined",
    "Limits",
    "LocalProtocolError",
    "Message",
    "PeerJoined",
    "PeerLeft",
    "Ping",
    "Pong",
    "PoseUpdate",
    "ProtocolError",
    "ProtocolViolation",
    "RemoteProtocolError",
    "Role",
    "ServerSession",
    "SessionStatistics",
    "SetRate",
    "Snapshot",
    "State",
    "UserEvent",
    "Welcome",
    "bytes_per_pose",
    "close_reason",
    "decode_message",
    "encode_message",
    "encode_snapshot",
    "encode_update",
    "frame_size",
    "is_valid_stream_name",
    "pose_problem",
]
