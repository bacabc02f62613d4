"""Sessions: one object per connection end, holding state and enforcing the rules.

``receive_data(frame)`` takes one complete websocket message and returns the
events it carries (today always zero or one); it never raises for anything the
peer sent. ``send(message)`` checks that this side may send it now and returns
the frame bytes; it raises ``LocalProtocolError`` for a local mistake. Neither
touches a socket or a clock.

The state table is in ``protocol._state``. On top of it, sessions check what
depends on limits and on what was agreed earlier:

- hello/welcome: same ``PROTOCOL_VERSION``;
- join: at most ``max_streams`` valid, distinct names, rate (or an auto
  rate's ``max_rate``) in [min_rate, max_rate] (the client checks against the limits its welcome
  announced, the server against its own ``Limits``);
- joined: the stream ids the server assigns become the user's own; the names
  must be those of the join;
- update: at most as many entries as owned streams, every stream owned and
  named once, every pose finite with a unit quaternion (else the update is
  dropped with a non-fatal "bad-pose"), of the variant agreed at join (velocity
  records exactly when the join said ``sends_velocities``; else a fatal
  "bad-message"), every velocity finite (else a non-fatal "bad-velocity");
- event: its stream owned by the sender, payload small enough; the server
  session stamps the sender's user id on it;
- shared objects (``protocol.objects``): the streams of the objects a user owns
  are its own while it owns them (:meth:`_Session.hold` / :meth:`_Session.let_go`;
  the client session follows ``object`` and ``owner`` messages by itself). An
  update entry for an object the server session knows (``objects``) but the user
  does not own is dropped with a non-fatal "object-not-owned" and the rest of
  the update goes on; ``object_create`` needs a unit quaternion ("bad-pose") and
  a valid name ("bad-stream-name");
- snapshot (client): of the variant the join asked for (``wants_velocities``;
  else a fatal "bad-message"), poses finite and unit, else dropped with
  "bad-pose", velocities finite, else dropped with "bad-velocity".

Compact updates (``Join.codec == "compact"``, see ``protocol._compact``): the
client session codes each update it sends as a codec update frame in the
welcome's volume (a position outside it: ``LocalProtocolError("bad-pose")``);
the server session takes a frame whose first byte is 0xC1 for one only when
compact was agreed (else it is no msgpack: a fatal "bad-frame"), refuses raw
update records then (a fatal "bad-message", as for the other velocity variant),
and returns the decoded ``PoseUpdate``, checked by the rules above. A position
decoded outside the volume is a non-fatal "bad-pose"; a frame coded against
baselines the server does not hold is a fatal "bad-baseline" (the codec's
``BaselineMismatch``).
"""

from __future__ import annotations

from collections.abc import Container, Mapping
from dataclasses import dataclass, replace
from typing import ClassVar

import msgpack
import numpy as np
from numpy.typing import NDArray

from posecast.protocol._compact import (
    CODEC_FRAME_BYTE,
    SnapshotDecoder,
    UpstreamDecoder,
    UpstreamEncoder,
)
from posecast.protocol._state import ERROR_FATAL, ERROR_JOIN, TRANSITIONS, Role, State, moves
from posecast.protocol.codec import DEFAULT_VOLUME, Volume
from posecast.protocol.errors import (
    ErrorCode,
    LocalProtocolError,
    ProtocolViolation,
    RemoteProtocolError,
)
from posecast.protocol.events import Event, Message, ProtocolError
from posecast.protocol.limits import DEFAULT_LIMITS, PROTOCOL_VERSION, Limits
from posecast.protocol.messages import (
    ErrorMessage,
    Hello,
    Join,
    Joined,
    PeerJoined,
    PeerLeft,
    RateNotice,
    SetRate,
    UserEvent,
    Welcome,
    is_valid_stream_name,
)
from posecast.protocol.objects import ObjectCreate, ObjectInfo, ObjectRemoved, Owner, unit_problem
from posecast.protocol.poses import (
    PoseUpdate,
    Snapshot,
    has_velocity,
    pose_problem,
    velocity_problem,
)
from posecast.protocol.wire import decode_message, encode_message

__all__ = ["ClientSession", "ServerSession", "SessionStatistics"]

# Which kinds each role may ever send, to tell "wrong side" from "wrong time".
_SENDABLE: dict[Role, frozenset[str]] = {
    role: frozenset(kind for table in TRANSITIONS.values() for (r, kind) in table if r is role)
    for role in Role
}

# (sender, state) -> {kind: next state}, precomputed for the hot path.
_MOVES: dict[tuple[Role, State], dict[str, State]] = {
    (role, state): moves(role, state) for role in Role for state in State
}

_TOO_EARLY = {
    State.START: "before hello",
    State.HELLO: "before welcome",
    State.READY: "before join",
    State.JOINING: "before joined",
    State.JOINED: "while joined",
    State.CLOSED: "after the session closed",
}


def _kind(message: Message) -> str:
    if type(message) is ErrorMessage:
        if message.fatal:
            return ERROR_FATAL
        if message.in_reply_to == "join":
            return ERROR_JOIN
    return message.TYPE


@dataclass(frozen=True, slots=True)
class SessionStatistics:
    """Counters of one session since it was created."""

    state: State
    frames_received: int
    bytes_received: int
    frames_sent: int
    bytes_sent: int
    errors: int
    """ProtocolError events returned by receive_data."""


class _Session:
    """What client and server sessions share: the state walk and the counters."""

    ROLE: ClassVar[Role]
    PEER: ClassVar[Role]

    def __init__(self, limits: Limits = DEFAULT_LIMITS) -> None:
        self.limits = limits
        self.state = State.START
        self._peer_moves = _MOVES[self.PEER, State.START]
        self.user: int | None = None
        """This session's user id, from welcome."""
        self.room: str | None = None
        self.streams: dict[str, int] = {}
        """The user's own streams, name -> id, from joined."""
        self.rate: float | None = None
        """The agreed update rate in Hz, from joined and accepted set_rate."""
        self._owned: frozenset[int] = frozenset()
        self._pending_join: Join | None = None
        self.sends_velocities = False
        """Agreed at join: the client's updates are of the velocity variant."""
        self.wants_velocities = False
        """Agreed at join: the client's snapshots are of the velocity variant."""
        self.codec = "raw"
        """Agreed at join: how the client's updates are coded (``Join.codec``)."""
        self.volume: Volume = DEFAULT_VOLUME
        """The room volume of compact updates: the server's, announced in welcome."""
        self._frames_in = self._bytes_in = self._frames_out = self._bytes_out = 0
        self._errors = 0
        #: Shared objects this user owns now (their streams are in ``_owned`` too).
        self.held: set[int] = set()
        #: Errors found beside the message of the frame being received.
        self._also: list[ProtocolError] = []

    @property
    def closed(self) -> bool:
        """Whether the session is over (bye or a fatal error)."""
        return self.state is State.CLOSED

    @property
    def owned_streams(self) -> frozenset[int]:
        """Ids of the streams assigned to this user (and the shared objects it owns)."""
        return self._owned

    def hold(self, stream: int) -> None:
        """Shared object ``stream`` is this user's now: its updates may carry it."""
        self.held.add(stream)
        self._owned = self._owned | {stream}

    def let_go(self, stream: int) -> None:
        """Shared object ``stream`` is no longer this user's."""
        if stream in self.held:
            self.held.discard(stream)
            self._owned = self._owned - {stream}

    def statistics(self) -> SessionStatistics:
        """A frozen copy of the counters."""
        return SessionStatistics(
            self.state,
            self._frames_in,
            self._bytes_in,
            self._frames_out,
            self._bytes_out,
            self._errors,
        )

    def receive_data(self, data: bytes | bytearray | memoryview | str) -> list[Event]:
        """Events carried by one complete websocket message from the peer; never raises.

        A text frame (``str``) is a fatal bad-frame: posecast frames are binary.
        """
        if self.state is State.CLOSED:
            return []
        self._frames_in += 1
        self._bytes_in += len(data)
        type_: str | None = None
        try:
            message = self._decode(data)
            type_ = message.TYPE
            new_state = self._peer_moves.get(_kind(message))
            if new_state is None:
                raise self._unexpected(message, self.PEER, type_)
            checked = self._check_received(message)
        except ProtocolViolation as exc:
            self._also.clear()
            self._errors += 1
            error = ProtocolError(exc.code, exc.message, exc.in_reply_to or type_)
            if error.fatal:
                self._move(State.CLOSED)
            return [error]
        if new_state is not self.state:
            self._move(new_state)
        if self._also:
            also, self._also = self._also, []
            self._errors += len(also)
            return [*also] if checked is None else [checked, *also]
        return [message if checked is None else checked]

    def send(self, message: Message) -> bytes:
        """Frame bytes of ``message``; raises LocalProtocolError if it may not be sent now."""
        new_state = _MOVES[self.ROLE, self.state].get(_kind(message))
        if new_state is None:
            exc = self._unexpected(message, self.ROLE, message.TYPE)
            raise LocalProtocolError(exc.code, f"cannot send {exc.message}")
        try:
            self._check_sent(message)
        except LocalProtocolError:
            raise
        except ProtocolViolation as exc:
            raise LocalProtocolError(exc.code, exc.message) from None
        data = self._encode(message)
        if len(data) > self.limits.max_frame_size:
            raise LocalProtocolError(
                ErrorCode.FRAME_TOO_LARGE,
                f"frame of {len(data)} bytes over {self.limits.max_frame_size}",
            )
        self._sent(message)
        self._move(new_state)
        self._frames_out += 1
        self._bytes_out += len(data)
        return data

    def _move(self, state: State) -> None:
        self.state = state
        self._peer_moves = _MOVES[self.PEER, state]

    def _unexpected(self, message: Message, sender: Role, type_: str) -> ProtocolViolation:
        if _kind(message) not in _SENDABLE[sender]:
            text = f"{type_} from a {sender.value}"
        else:
            text = f"{type_} {_TOO_EARLY[self.state]}"
        return ProtocolViolation(ErrorCode.UNEXPECTED_MESSAGE, text)

    def _decode(self, data: bytes | bytearray | memoryview | str) -> Message:
        """The message of one received frame; raises RemoteProtocolError."""
        return decode_message(data, max_frame_size=self.limits.max_frame_size)

    def _encode(self, message: Message) -> bytes:
        """The frame bytes of a message that may be sent now; raises LocalProtocolError."""
        return encode_message(message)

    def _check_received(self, message: Message) -> Message | None:
        """Role rules for an incoming message; may return it amended (None: nothing of it
        is left, the errors in ``_also`` say why). Raises ProtocolViolation."""
        raise NotImplementedError

    def _check_sent(self, message: Message) -> None:
        """Role rules for an outgoing message, applied before it is encoded."""
        raise NotImplementedError

    def _sent(self, message: Message) -> None:
        """Record what an outgoing message settles, once it is surely sent."""

    # Shared checks -------------------------------------------------------

    def _check_update(
        self, update: PoseUpdate, decoded: bool = False, ids: list[int] | None = None
    ) -> None:
        """Stream ownership and the records; ``decoded``: a compact update, whose poses and
        velocities the codec made from valid codes (finite, unit: not checked again);
        ``ids``: its stream ids, if its decoder listed them (then not read again)."""
        entries = update.entries
        owned = self._owned
        if len(entries) > len(owned):
            raise ProtocolViolation(
                ErrorCode.TOO_MANY_STREAMS,
                f"update has {len(entries)} poses for {len(owned)} streams",
            )
        if ids is None or len(ids) != len(entries):
            ids = entries["stream"].tolist()
        seen = set(ids)
        if not seen <= owned:
            raise ProtocolViolation(
                ErrorCode.STREAM_NOT_OWNED, f"stream {min(seen - owned)} not owned"
            )
        if len(seen) != len(ids):
            raise ProtocolViolation(ErrorCode.DUPLICATE_STREAM, "stream twice in one update")
        self._check_records("update", entries, self.sends_velocities, decoded)

    @staticmethod
    def _check_records(
        type_: str, entries: NDArray[np.void], agreed: bool, decoded: bool = False
    ) -> None:
        """A pose frame's records: the variant agreed at join, usable poses and velocities
        (``decoded``: dequantised from valid codec codes, hence usable; tests check it)."""
        velocity = has_velocity(entries)
        if velocity and not agreed:
            raise ProtocolViolation(
                ErrorCode.BAD_MESSAGE, f"{type_} with velocities, not agreed at join"
            )
        if agreed and not velocity:
            raise ProtocolViolation(
                ErrorCode.BAD_MESSAGE, f"{type_} without velocities, agreed at join"
            )
        if decoded:
            return
        problem = pose_problem(entries)
        if problem is not None:
            raise ProtocolViolation(ErrorCode.BAD_POSE, problem)
        problem = velocity_problem(entries)
        if problem is not None:
            raise ProtocolViolation(ErrorCode.BAD_VELOCITY, problem)

    def _agree_join(self) -> None:
        """Settle what the join asked for (variants, codec): joined accepted it."""
        join = self._pending_join
        assert join is not None  # joined is checked against the pending join first
        self.sends_velocities = join.sends_velocities
        self.wants_velocities = join.wants_velocities
        self.codec = join.codec

    def _check_event(self, event: UserEvent) -> None:
        if event.user is not None and event.user != self.user:
            raise ProtocolViolation(ErrorCode.BAD_MESSAGE, "event.user is not the sender")
        if event.stream is not None and event.stream not in self._owned:
            raise ProtocolViolation(ErrorCode.STREAM_NOT_OWNED, f"stream {event.stream} not owned")
        size = len(msgpack.packb(event.payload))
        if size > self.limits.max_event_payload:
            raise ProtocolViolation(
                ErrorCode.PAYLOAD_TOO_LARGE,
                f"event payload of {size} bytes over {self.limits.max_event_payload}",
            )

    def _check_names(self, names: tuple[str, ...], max_streams: int) -> None:
        if len(names) > max_streams:
            raise ProtocolViolation(
                ErrorCode.TOO_MANY_STREAMS, f"{len(names)} streams, at most {max_streams}"
            )
        if not names:
            raise ProtocolViolation(ErrorCode.BAD_STREAM_NAME, "no streams")
        for name in names:
            if not is_valid_stream_name(name, self.limits.max_stream_name_length):
                raise ProtocolViolation(ErrorCode.BAD_STREAM_NAME, f"bad stream name {name[:40]!r}")
        if len(set(names)) != len(names):
            raise ProtocolViolation(ErrorCode.BAD_STREAM_NAME, "duplicate stream name")

    @staticmethod
    def _check_rate(rate: float, lo: float, hi: float) -> None:
        if not lo <= rate <= hi:
            raise ProtocolViolation(
                ErrorCode.BAD_RATE, f"rate {rate:g} hz outside [{lo:g}, {hi:g}]"
            )

    @classmethod
    def _check_join_rate(cls, join: Join, lo: float, hi: float) -> None:
        """A join's rate in range; an auto rate's ``max_rate``, if given, too."""
        if not join.auto_rate:
            cls._check_rate(float(join.rate), lo, hi)
        elif join.max_rate is not None:
            cls._check_rate(join.max_rate, lo, hi)

    def _accept_joined(self, joined: Joined) -> None:
        join = self._pending_join
        if join is None or joined.room != join.room or set(joined.streams) != set(join.streams):
            raise ProtocolViolation(ErrorCode.BAD_MESSAGE, "joined does not match the join")


class ServerSession(_Session):
    """The server's end of one connection.

    The server assigns the user id in ``welcome`` (see ``make_welcome``) and the
    stream ids in ``joined``; sending them through this session is what makes
    them the user's own. Snapshots usually bypass the session: encode them once
    with ``encode_snapshot`` and send the same bytes to every due subscriber.
    """

    ROLE = Role.SERVER
    PEER = Role.CLIENT

    def __init__(self, limits: Limits = DEFAULT_LIMITS, volume: Volume = DEFAULT_VOLUME) -> None:
        super().__init__(limits)
        self.volume = volume
        self._upstream: UpstreamDecoder | None = None
        # The update the last compact frame decoded to (raw records are refused then).
        self._compact_update: PoseUpdate | None = None
        #: Stream ids of the room's shared objects (the server keeps it up to date).
        self.objects: Container[int] = ()

    def make_welcome(self, user: int, server_time: float) -> Welcome:
        """A welcome that announces this session's limits and room volume."""
        volume = self.volume
        return Welcome(
            user=user,
            server_time=server_time,
            min_rate=self.limits.min_rate,
            max_rate=self.limits.max_rate,
            max_streams=self.limits.max_streams,
            volume=(*volume.lo, *volume.hi),
        )

    def _decode(self, data: bytes | bytearray | memoryview | str) -> Message:
        upstream = self._upstream
        if upstream is None or isinstance(data, str) or data[:1] != bytes([CODEC_FRAME_BYTE]):
            return decode_message(data, max_frame_size=self.limits.max_frame_size)
        if len(data) > self.limits.max_frame_size:
            raise RemoteProtocolError(
                ErrorCode.FRAME_TOO_LARGE,
                f"frame of {len(data)} bytes over {self.limits.max_frame_size}",
            )
        update = upstream.decode(data)
        self._compact_update = update
        return update

    def compact_codes(self) -> dict[int, list[int]] | None:
        """Stream id -> codes of the last update received, if compact was agreed
        (then every update is a compact frame), else None."""
        upstream = self._upstream
        return None if upstream is None else upstream.last_codes

    def assign_streams(self, streams: Mapping[str, int]) -> None:
        """Make these stream ids the user's own without sending joined (tests, replays)."""
        self.streams = dict(streams)
        self._owned = frozenset(self.streams.values()) | self.held

    def _strip_stray_objects(self, update: PoseUpdate) -> PoseUpdate | None:
        """``update`` without entries for shared objects this user does not own."""
        objects, owned = self.objects, self._owned
        if not objects:
            return update
        ids = update.entries["stream"]
        stray = sorted(s for s in set(ids.tolist()) if s not in owned and s in objects)
        if not stray:
            return update
        self._also.append(
            ProtocolError(
                ErrorCode.OBJECT_NOT_OWNED, f"object stream {stray[0]} not owned", "update"
            )
        )
        keep = ~np.isin(ids, stray)
        return replace(update, entries=update.entries[keep]) if keep.any() else None

    def _check_received(self, message: Message) -> Message | None:
        if isinstance(message, PoseUpdate):
            if self._upstream is not None and message is not self._compact_update:
                raise ProtocolViolation(
                    ErrorCode.BAD_MESSAGE, "update of raw records, compact agreed at join"
                )
            self._compact_update = None
            update = self._strip_stray_objects(message)
            if update is not None:
                upstream = self._upstream
                # A compact update's ids are its decoder's codes' keys (one per stream).
                ids = list(upstream.last_codes) if upstream and update is message else None
                self._check_update(update, decoded=upstream is not None, ids=ids)
            return update
        elif isinstance(message, ObjectCreate):
            if not is_valid_stream_name(message.name, self.limits.max_stream_name_length):
                raise ProtocolViolation(
                    ErrorCode.BAD_STREAM_NAME, f"bad object name {message.name[:40]!r}"
                )
            problem = unit_problem(message.pose)
            if problem is not None:
                raise ProtocolViolation(ErrorCode.BAD_POSE, f"object_create: {problem}")
        elif isinstance(message, Join):
            self._check_names(message.streams, self.limits.max_streams)
            self._check_join_rate(message, self.limits.min_rate, self.limits.max_rate)
            self._pending_join = message
        elif isinstance(message, SetRate):
            self._check_rate(message.rate, self.limits.min_rate, self.limits.max_rate)
            self.rate = message.rate
        elif isinstance(message, UserEvent):
            self._check_event(message)
            return replace(message, user=self.user)
        return message

    def _check_sent(self, message: Message) -> None:
        if isinstance(message, Welcome):
            if message.version != PROTOCOL_VERSION:
                raise ProtocolViolation(ErrorCode.VERSION_MISMATCH, "welcome of another version")
        elif isinstance(message, Joined):
            self._accept_joined(message)
            self._check_names(tuple(message.streams), self.limits.max_streams)
            self._check_rate(message.rate, self.limits.min_rate, self.limits.max_rate)

    def _sent(self, message: Message) -> None:
        if isinstance(message, Welcome):
            self.user = message.user
        elif isinstance(message, Joined):
            self.room = message.room
            self.rate = message.rate
            self.assign_streams(message.streams)
            self._agree_join()
            if self.codec == "compact":
                self._upstream = UpstreamDecoder(self.volume)
        elif isinstance(message, RateNotice):
            self.rate = message.rate


class ClientSession(_Session):
    """The client's end of one connection.

    Joins are checked against the limits the server announced in welcome.
    ``peers`` follows peer_joined/peer_left: user id -> (stream name -> id).
    """

    ROLE = Role.CLIENT
    PEER = Role.SERVER

    def __init__(self, limits: Limits = DEFAULT_LIMITS) -> None:
        super().__init__(limits)
        self.welcome: Welcome | None = None
        self.peers: dict[int, dict[str, int]] = {}
        #: The room's shared objects, name -> stream id (joined, object, object_removed).
        self.objects: dict[str, int] = {}
        self._upstream: UpstreamEncoder | None = None
        self._snapshots: SnapshotDecoder | None = None

    def _decode(self, data: bytes | bytearray | memoryview | str) -> Message:
        snapshots = self._snapshots
        if snapshots is None or isinstance(data, str) or data[:1] != bytes([CODEC_FRAME_BYTE]):
            return decode_message(data, max_frame_size=self.limits.max_frame_size)
        if len(data) > self.limits.max_frame_size:
            raise RemoteProtocolError(
                ErrorCode.FRAME_TOO_LARGE,
                f"frame of {len(data)} bytes over {self.limits.max_frame_size}",
            )
        return snapshots.decode(data)

    def _encode(self, message: Message) -> bytes:
        if self._upstream is not None and isinstance(message, PoseUpdate):
            return self._upstream.encode(message)
        return encode_message(message)

    def _check_received(self, message: Message) -> Message | None:
        if isinstance(message, Snapshot):
            self._check_records("snapshot", message.entries, self.wants_velocities)
        elif isinstance(message, Welcome):
            self.welcome = message
            self.user = message.user
            self.volume = message.room_volume
        elif isinstance(message, Joined):
            self._accept_joined(message)
            self.room = message.room
            self.rate = message.rate
            self.streams = dict(message.streams)
            self.objects = dict(message.objects)
            self._owned = frozenset(self.streams.values()) | self.held
            self._agree_join()
            if self.codec == "compact":
                self._upstream = UpstreamEncoder(self.volume)
                self._snapshots = SnapshotDecoder(self.volume)
        elif isinstance(message, RateNotice):
            self.rate = message.rate
        elif isinstance(message, PeerJoined):
            self.peers[message.user] = dict(message.streams)
        elif isinstance(message, ObjectInfo):
            self.objects[message.name] = message.stream
            self._follow_owner(message.stream, message.owner)
        elif isinstance(message, Owner):
            self._follow_owner(message.stream, message.owner)
        elif isinstance(message, ObjectRemoved):
            self.let_go(message.stream)
            self.objects = {n: s for n, s in self.objects.items() if s != message.stream}
        elif isinstance(message, PeerLeft):
            self.peers.pop(message.user, None)
            # Its snapshot baselines stay: a snapshot encoded before it left may
            # still follow (events overtake the pose slot), and a user or stream id
            # given out again always starts with key entries, which overwrite them.
        return message

    def _follow_owner(self, stream: int, owner: int | None) -> None:
        if owner is not None and owner == self.user:
            self.hold(stream)
        else:
            self.let_go(stream)

    def _check_sent(self, message: Message) -> None:
        if isinstance(message, PoseUpdate):
            self._check_update(message)
        elif isinstance(message, Hello):
            if message.version != PROTOCOL_VERSION:
                raise ProtocolViolation(ErrorCode.VERSION_MISMATCH, "hello of another version")
        elif isinstance(message, Join):
            welcome = self.welcome
            assert welcome is not None  # the state table only allows join after welcome
            self._check_names(message.streams, min(welcome.max_streams, self.limits.max_streams))
            self._check_join_rate(message, welcome.min_rate, welcome.max_rate)
        elif isinstance(message, SetRate):
            welcome = self.welcome
            assert welcome is not None
            self._check_rate(message.rate, welcome.min_rate, welcome.max_rate)
        elif isinstance(message, UserEvent):
            self._check_event(message)

    def _sent(self, message: Message) -> None:
        if isinstance(message, Join):
            self._pending_join = message
        elif self._upstream is not None and isinstance(message, PoseUpdate):
            self._upstream.commit()
