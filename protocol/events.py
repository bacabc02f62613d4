"""What sessions hand back: the ``Message`` and ``Event`` unions and ``ProtocolError``.

``Session.receive_data`` returns events: every wire message (control messages,
``PoseUpdate``, ``Snapshot``) plus ``ProtocolError``, which never travels: it is
this side's verdict on something the peer sent. To tell the peer, send
``error.to_message()``; if ``error.fatal``, then close the websocket with
``error.close_code`` and ``error.close_reason``.
"""

from __future__ import annotations

from dataclasses import dataclass

from posecast.protocol.errors import ErrorCode, close_reason
from posecast.protocol.messages import (
    Bye,
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
from posecast.protocol.objects import (
    ObjectCreate,
    ObjectInfo,
    ObjectRemoved,
    Owner,
    Release,
    RequestOwnership,
)
from posecast.protocol.poses import PoseUpdate, Snapshot

__all__ = ["Event", "Message", "ProtocolError"]

Message = (
    Hello
    | Welcome
    | Join
    | Joined
    | PeerJoined
    | PeerLeft
    | PeerStalled
    | PeerResumed
    | Ping
    | Pong
    | SetRate
    | RateNotice
    | Renew
    | UserEvent
    | ErrorMessage
    | Bye
    | ObjectCreate
    | RequestOwnership
    | Release
    | ObjectInfo
    | Owner
    | ObjectRemoved
    | PoseUpdate
    | Snapshot
)
"""Anything that travels as one websocket frame."""


@dataclass(frozen=True, slots=True)
class ProtocolError:
    """The peer broke the protocol; ``code`` says how (see ``protocol.errors``)."""

    code: ErrorCode
    message: str
    """Short lowercase description, e.g. "join before hello"."""
    in_reply_to: str | None = None
    """Type of the offending message when it was recognised ("join", "update", ...)."""

    @property
    def fatal(self) -> bool:
        """Whether the session is over (it is CLOSED already)."""
        return self.code.fatal

    @property
    def close_code(self) -> int | None:
        """Suggested websocket close code (1002, 1008, 1009), None if not fatal."""
        return self.code.close_code

    @property
    def close_reason(self) -> str:
        """``message`` cut to fit a websocket close frame (123 bytes)."""
        return close_reason(self.message)

    def to_message(self) -> ErrorMessage:
        """The "error" message that tells the peer about this error."""
        return ErrorMessage.from_code(self.code, self.message, in_reply_to=self.in_reply_to)


Event = Message | ProtocolError
"""What ``receive_data`` returns: a message from the peer, or a verdict on it."""
