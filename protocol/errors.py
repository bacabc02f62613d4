"""Every way a posecast session can go wrong: one exception tree, one code table.

Exceptions::

    PosecastError                 root of every user-facing posecast error (also the
    │                             recorder's, the tiers', the tokens'...): the CLI turns
    │                             any of them into one line on stderr and an exit code
    └── ProtocolViolation         base: .code (ErrorCode), .message, .in_reply_to,
        │                         .fatal, .close_code
        ├── LocalProtocolError    this side tried to build or send something invalid
        │                         (a bug here): raised by message constructors and
        │                         Session.send(); never caused by the peer
        └── RemoteProtocolError   the peer sent something invalid: raised only by the
                                  plain decoders (decode_message); Session.receive_data()
                                  never raises it but returns a ProtocolError event

Error codes (``ErrorCode``, a ``StrEnum``: the values travel in ``error`` messages).
"fatal" means the session is over: it moves to CLOSED and the server should close
the websocket with the suggested close code and the message as reason. A non-fatal
error drops the one offending message; the session goes on.

==================  =====  =====  =====================================================
code                fatal  close  raised when
==================  =====  =====  =====================================================
bad-frame           yes    1002   not msgpack, truncated, trailing bytes, not a map,
                                  no string "type"
frame-too-large     yes    1009   a frame is longer than ``max_frame_size``
unknown-type        yes    1002   a well-formed frame with a "type" this version lacks
bad-message         yes    1002   a known type with missing, unknown or ill-typed
                                  fields, or values out of their range (NaN in a
                                  control field, user id over u16, ...); a pose
                                  frame of the other variant than agreed at join
                                  (velocity records without sends/wants_velocities,
                                  or plain records with it; raw update records
                                  after join agreed codec "compact")
bad-baseline        yes    1002   a compact delta frame (update or snapshot) coded
                                  against other baselines than the receiver holds,
                                  or naming a stream it holds none for
                                  (``BaselineMismatch``): the chain is broken and
                                  nothing of the frame is shown
version-mismatch    yes    1002   hello/welcome carry another ``PROTOCOL_VERSION``
unexpected-message  yes    1002   a message the state table forbids: anything before
                                  hello, join twice, poses before joined, a
                                  server-only type from a client, ...
stream-not-owned    yes    1008   an update or event names a stream id not assigned to
                                  this user (another user's, or never assigned)
too-many-streams    no     --     a join lists more than ``max_streams`` names, or an
                                  update carries more entries than the user owns
duplicate-stream    no     --     one update carries the same stream id twice
bad-stream-name     no     --     a join has an invalid, duplicate or too long name
bad-pose            no     --     a pose with NaN/inf, or a quaternion norm off 1 by
                                  more than ``QUAT_NORM_TOLERANCE``, or (compact
                                  updates) a position outside the room volume
bad-velocity        no     --     a velocity-variant pose whose velocity holds NaN/inf
                                  (float16 on the wire)
bad-rate            no     --     join/set_rate asks for a rate outside
                                  [min_rate, max_rate] (the request is refused, never
                                  clamped)
payload-too-large   no     --     an event payload encodes to more than
                                  ``max_event_payload`` bytes
unauthorized        yes    1008   (server decision) bad access token
room-full           no     --     (server decision) join refused, try later
user-taken          no     --     (server decision) the token's user is already live
                                  in that room on another connection (one connection
                                  per room and user)
ownership-refused   no     --     (server decision) a shared object's request,
                                  release or creation refused: held by another (not
                                  stealable, or locked), not held by the sender, no
                                  such object, a name taken, over ``max_objects``
object-not-owned    no     --     an update names a shared object's stream that
                                  the sender does not own (any more): those entries
                                  are dropped, the rest of the update is taken
bad-room            no     --     (server decision) a room name that is empty once
                                  stripped, over 64 bytes, or holds control or bidi
                                  override characters
too-slow            yes    1008   (server decision) a peer's event queue overflowed
server-full         yes    1013   (server decision) the relay is at its measured
                                  capacity: a hello or join refused at once (when
                                  to retry: in the message, and ``retry_after``
                                  if the hello asked); try later or another relay
internal-error      yes    1011   (server decision) a bug on the server
==================  =====  =====  =====================================================

Codes marked "(server decision)" are never produced by ``protocol`` itself; they
are listed so that the server's own refusals use the same codes, fatality and
close codes.
"""

from __future__ import annotations

from enum import StrEnum

__all__ = [
    "MAX_CLOSE_REASON_BYTES",
    "ErrorCode",
    "LocalProtocolError",
    "PosecastError",
    "ProtocolViolation",
    "RemoteProtocolError",
    "close_reason",
]

# RFC 6455 leaves 123 bytes for the reason in a close frame (125 minus the code).
MAX_CLOSE_REASON_BYTES = 123


class ErrorCode(StrEnum):
    """Error codes on the wire; see the module docstring for when each is used."""

    BAD_FRAME = "bad-frame"
    FRAME_TOO_LARGE = "frame-too-large"
    UNKNOWN_TYPE = "unknown-type"
    BAD_MESSAGE = "bad-message"
    BAD_BASELINE = "bad-baseline"
    VERSION_MISMATCH = "version-mismatch"
    UNEXPECTED_MESSAGE = "unexpected-message"
    STREAM_NOT_OWNED = "stream-not-owned"
    TOO_MANY_STREAMS = "too-many-streams"
    DUPLICATE_STREAM = "duplicate-stream"
    BAD_STREAM_NAME = "bad-stream-name"
    BAD_POSE = "bad-pose"
    BAD_VELOCITY = "bad-velocity"
    BAD_RATE = "bad-rate"
    PAYLOAD_TOO_LARGE = "payload-too-large"
    UNAUTHORIZED = "unauthorized"
    ROOM_FULL = "room-full"
    USER_TAKEN = "user-taken"
    OWNERSHIP_REFUSED = "ownership-refused"
    OBJECT_NOT_OWNED = "object-not-owned"
    BAD_ROOM = "bad-room"
    TOO_SLOW = "too-slow"
    SERVER_FULL = "server-full"
    INTERNAL_ERROR = "internal-error"

    @property
    def fatal(self) -> bool:
        """Whether this error ends the session."""
        return _CLOSE_CODES[self] is not None

    @property
    def close_code(self) -> int | None:
        """Suggested websocket close code, or None for a non-fatal error."""
        return _CLOSE_CODES[self]


# 1002 protocol error, 1008 policy violation, 1009 message too big, 1011 server bug,
# 1013 try again later.
_CLOSE_CODES: dict[ErrorCode, int | None] = {
    ErrorCode.BAD_FRAME: 1002,
    ErrorCode.FRAME_TOO_LARGE: 1009,
    ErrorCode.UNKNOWN_TYPE: 1002,
    ErrorCode.BAD_MESSAGE: 1002,
    ErrorCode.BAD_BASELINE: 1002,
    ErrorCode.VERSION_MISMATCH: 1002,
    ErrorCode.UNEXPECTED_MESSAGE: 1002,
    ErrorCode.STREAM_NOT_OWNED: 1008,
    ErrorCode.TOO_MANY_STREAMS: None,
    ErrorCode.DUPLICATE_STREAM: None,
    ErrorCode.BAD_STREAM_NAME: None,
    ErrorCode.BAD_POSE: None,
    ErrorCode.BAD_VELOCITY: None,
    ErrorCode.BAD_RATE: None,
    ErrorCode.PAYLOAD_TOO_LARGE: None,
    ErrorCode.UNAUTHORIZED: 1008,
    ErrorCode.ROOM_FULL: None,
    ErrorCode.USER_TAKEN: None,
    ErrorCode.OWNERSHIP_REFUSED: None,
    ErrorCode.OBJECT_NOT_OWNED: None,
    ErrorCode.BAD_ROOM: None,
    ErrorCode.TOO_SLOW: 1008,
    ErrorCode.SERVER_FULL: 1013,
    ErrorCode.INTERNAL_ERROR: 1011,
}


def close_reason(message: str) -> str:
    """Cut ``message`` to what fits in a websocket close frame, on a character boundary."""
    data = message.encode("utf-8")[:MAX_CLOSE_REASON_BYTES]
    return data.decode("utf-8", errors="ignore")


class PosecastError(Exception):
    """Root of the errors a user can cause and fix: a bad file, argument or setting.

    Its message is one line that says what was wrong (and, where it helps, what to
    do); the command line prints it without a traceback. ``protocol`` imports
    nothing else of ours, so every other package can derive from this root.
    """


class ProtocolViolation(PosecastError):
    """Base of posecast protocol errors: a code from the table and a short message."""

    def __init__(self, code: ErrorCode, message: str, *, in_reply_to: str | None = None) -> None:
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message
        self.in_reply_to = in_reply_to
        """Type of the offending message, when it was recognised."""

    @property
    def fatal(self) -> bool:
        """Whether this error ends the session."""
        return self.code.fatal

    @property
    def close_code(self) -> int | None:
        """Suggested websocket close code, or None for a non-fatal error."""
        return self.code.close_code


class LocalProtocolError(ProtocolViolation):
    """This side tried to build or send an invalid message."""


class RemoteProtocolError(ProtocolViolation):
    """The peer sent an invalid message (only plain decoders raise this)."""
