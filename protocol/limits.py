"""Protocol version and the limits a session enforces, as constants and as ``Limits``.

The constants are the defaults; a session takes a ``Limits`` to change them (for
example a client in a large room needs a bigger ``max_frame_size`` for snapshots:
every pose costs 36 bytes, 48 in the velocity variant, so 64 KiB hold about 1800
poses, or 1360 with velocities).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from posecast.protocol.errors import ErrorCode, LocalProtocolError

__all__ = [
    "DEFAULT_LIMITS",
    "MAX_EVENT_PAYLOAD",
    "MAX_FRAME_SIZE",
    "MAX_PAYLOAD_DEPTH",
    "MAX_RATE",
    "MAX_STREAMS_PER_USER",
    "MAX_STREAM_NAME_LENGTH",
    "MAX_TEXT_LENGTH",
    "MIN_RATE",
    "PROTOCOL_VERSION",
    "QUAT_NORM_TOLERANCE",
    "Limits",
]

PROTOCOL_VERSION = 1
"""Bumped on any change to the wire format; both sides must agree exactly."""

MAX_FRAME_SIZE = 64 * 1024
"""Longest websocket message a session accepts, in bytes."""

MAX_STREAMS_PER_USER = 16
"""Most streams (devices plus objects) one user may join with."""

MAX_STREAM_NAME_LENGTH = 32
"""Longest stream name, in characters (``object:`` included)."""

MAX_EVENT_PAYLOAD = 4096
"""Largest event payload, in bytes once msgpack-encoded."""

MIN_RATE = 5.0
"""Lowest update rate a user may request, in Hz."""

MAX_RATE = 30.0
"""Highest update rate a user may request, in Hz."""

MAX_TEXT_LENGTH = 256
"""Longest free-text field (room, token, label, agent, reasons, error messages)."""

MAX_PAYLOAD_DEPTH = 8
"""Deepest nesting of lists and maps inside an event payload."""

QUAT_NORM_TOLERANCE = 1e-3
"""How far from 1 a pose quaternion's norm may be (float32 rounding is ~1e-7)."""


@dataclass(frozen=True, slots=True)
class Limits:
    """The limits one session enforces on what it sends and receives."""

    max_frame_size: int = MAX_FRAME_SIZE
    max_streams: int = MAX_STREAMS_PER_USER
    max_stream_name_length: int = MAX_STREAM_NAME_LENGTH
    max_event_payload: int = MAX_EVENT_PAYLOAD
    min_rate: float = MIN_RATE
    max_rate: float = MAX_RATE

    def __post_init__(self) -> None:
        for name in ("max_frame_size", "max_streams", "max_stream_name_length"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise LocalProtocolError(ErrorCode.BAD_MESSAGE, f"{name} must be an int >= 1")
        payload = self.max_event_payload
        if isinstance(payload, bool) or not isinstance(payload, int) or payload < 0:
            raise LocalProtocolError(ErrorCode.BAD_MESSAGE, "max_event_payload must be an int >= 0")
        # Stream ids are u16, so no user can own more than 65536 of them.
        if self.max_streams > 1 << 16:
            raise LocalProtocolError(ErrorCode.BAD_MESSAGE, "max_streams must be <= 65536")
        lo, hi = self.min_rate, self.max_rate
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo <= hi):
            raise LocalProtocolError(
                ErrorCode.BAD_MESSAGE, "rates must be finite with 0 < min_rate <= max_rate"
            )


DEFAULT_LIMITS = Limits()
