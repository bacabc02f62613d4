"""Control messages: frozen dataclasses that validate their fields on construction.

Each class is one msgpack map on the wire, ``{"type": TYPE, field: value, ...}``
with the dataclass fields as keys in declaration order. Decoding accepts a
missing key only for fields with a default, and rejects unknown keys (the
schema is pinned by ``PROTOCOL_VERSION``). Optional capabilities added later
(the velocity flags of join and peer_joined, ``Join.codec``, ``Join.spectator``,
``Welcome.volume``)
are left out of the map while they hold their default, so a peer that does not
use them sends and receives the same bytes as before they existed.

Constructors check types and fixed ranges (u16 ids, finite numbers, string
lengths) and raise ``LocalProtocolError("bad-message")``. Checks that depend on
a session's ``Limits`` or state (rate range, stream names, ownership, version)
live in the session, so a peer can be told "bad-rate" instead of "bad-message".
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from dataclasses import MISSING, dataclass, field, fields
from typing import Any, ClassVar, Self, TypeVar

from posecast.protocol._validate import (
    U16_MAX,
    U63_MAX,
    bad,
    check_bool,
    check_float,
    check_int,
    check_optional_float,
    check_optional_int,
    check_optional_text,
    check_payload,
    check_stream_map,
    check_text,
)
from posecast.protocol.codec import DEFAULT_VOLUME, Volume
from posecast.protocol.errors import ErrorCode
from posecast.protocol.limits import (
    MAX_RATE,
    MAX_STREAM_NAME_LENGTH,
    MAX_STREAMS_PER_USER,
    MIN_RATE,
    PROTOCOL_VERSION,
)

__all__ = [
    "AUTO_RATE",
    "CODECS",
    "DEVICE_NAMES",
    "EVENT_KINDS",
    "OBJECT_PREFIX",
    "Bye",
    "ControlMessage",
    "ErrorMessage",
    "Hello",
    "Join",
    "Joined",
    "PeerJoined",
    "PeerLeft",
    "PeerResumed",
    "PeerStalled",
    "Ping",
    "Pong",
    "RateNotice",
    "Renew",
    "SetRate",
    "UserEvent",
    "Welcome",
    "is_valid_stream_name",
]

DEVICE_NAMES = ("head", "left", "right")
"""The tracked devices of a user, by convention; any lowercase identifier is a valid device."""

OBJECT_PREFIX = "object:"
"""Prefix of object stream names, e.g. ``object:drill``."""

# A device is a lowercase identifier; an object is "object:" plus a plain name.
_STREAM_NAME = re.compile(r"[a-z][a-z0-9_]*|object:[A-Za-z0-9_.\-]+")

EVENT_KINDS = frozenset({"grab", "release", "button", "scene_step"})
"""Values of ``UserEvent.kind``."""

AUTO_RATE = "auto"
"""``Join.rate`` of a client that lets the server choose its rate (``RateNotice``)."""

CODECS = ("raw", "compact")
"""Values of ``Join.codec``: how the client's updates are coded (``protocol.poses``
records, or ``protocol.codec`` update frames)."""

_DEFAULT_VOLUME_WIRE: tuple[float, float, float, float, float, float] = (
    *DEFAULT_VOLUME.lo,
    *DEFAULT_VOLUME.hi,
)
"""``Welcome.volume`` of the default room volume (then not sent): lo x, y, z, hi x, y, z."""

# Longest error code accepted from a peer: codes are short kebab-case words.
_MAX_CODE_LENGTH = 64


def _set(obj: object, name: str, value: object) -> None:
    # Frozen dataclasses normalise their own fields (int -> float, list -> tuple).
    object.__setattr__(obj, name, value)


class ControlMessage:
    """Base of the control messages: wire type, field names and the map codec."""

    __slots__ = ()

    TYPE: ClassVar[str]
    _NAMES: ClassVar[frozenset[str]]
    _REQUIRED: ClassVar[frozenset[str]]
    _ORDER: ClassVar[tuple[str, ...]]
    #: Fields left out of the map while they equal their default.
    _OMIT: ClassVar[dict[str, object]]

    def to_wire(self) -> dict[str, object]:
        """The msgpack map for this message, "type" first."""
        wire: dict[str, object] = {"type": self.TYPE}
        omit = self._OMIT
        for name in self._ORDER:
            value = getattr(self, name)
            if name in omit and value == omit[name]:
                continue
            wire[name] = value
        return wire

    @classmethod
    def from_wire(cls, wire: Mapping[str, object]) -> Self:
        """Build from a decoded map; raises LocalProtocolError (decoders re-raise as remote)."""
        keys = wire.keys() - {"type"}
        unknown = keys - cls._NAMES
        if unknown:
            # Quote at most 32 characters: the name comes from the peer.
            raise bad(cls.TYPE, f"has unknown field {sorted(map(str, unknown))[0][:32]!r}")
        missing = cls._REQUIRED - keys
        if missing:
            raise bad(cls.TYPE, f"lacks field {sorted(missing)[0]!r}")
        factory: Callable[..., Self] = cls
        return factory(**{name: wire[name] for name in keys})


_M = TypeVar("_M", bound=type[ControlMessage])

# Field metadata key: leave the field off the wire while it holds its default.
_OMIT_DEFAULT = "omit_default"


def _capability() -> Any:
    """An optional bool capability flag: False by default, and then not sent."""
    return field(default=False, metadata={_OMIT_DEFAULT: True})


def _omitted(default: object) -> Any:
    """An optional field added later: ``default`` unless given, and then not sent."""
    return field(default=default, metadata={_OMIT_DEFAULT: True})


def _register(cls: _M) -> _M:
    # Runs after @dataclass, so the field tables see the final fields.
    names = tuple(f.name for f in fields(cls))  # type: ignore[arg-type]
    cls._ORDER = names
    cls._NAMES = frozenset(names)
    cls._REQUIRED = frozenset(
        f.name
        for f in fields(cls)  # type: ignore[arg-type]
        if f.default is MISSING and f.default_factory is MISSING
    )
    cls._OMIT = {
        f.name: f.default if f.default is not MISSING else f.default_factory()  # type: ignore[operator]
        for f in fields(cls)  # type: ignore[arg-type]
        if f.metadata.get(_OMIT_DEFAULT)
    }
    return cls


def is_valid_stream_name(name: object, max_length: int = MAX_STREAM_NAME_LENGTH) -> bool:
    """Whether ``name`` is a device name or ``object:NAME``, at most ``max_length`` long."""
    return (
        type(name) is str and len(name) <= max_length and _STREAM_NAME.fullmatch(name) is not None
    )


@_register
@dataclass(frozen=True, slots=True)
class Hello(ControlMessage):
    """Client -> server, first message: the protocol version the client speaks."""

    TYPE: ClassVar[str] = "hello"
    version: int = PROTOCOL_VERSION
    agent: str = ""
    """Free text naming the client software, for logs."""
    resumable: bool = _capability()
    """This client reconnects by itself: if its connection drops, the server keeps
    its place in the room for a while (peers get ``peer_stalled``), and welcome
    gives it a ``resume`` token."""
    resume: str | None = _omitted(None)
    """The ``welcome.resume`` token of a dropped connection: same user id, and the
    next join of the same room and streams gets the same stream ids back."""
    wants_retry_after: bool = _capability()
    """A ``server-full`` refusal of this client carries ``error.retry_after``."""

    def __post_init__(self) -> None:
        check_int("hello.version", self.version, 0, U16_MAX)
        check_text("hello.agent", self.agent)
        check_bool("hello.resumable", self.resumable)
        check_optional_text("hello.resume", self.resume)
        check_bool("hello.wants_retry_after", self.wants_retry_after)


@_register
@dataclass(frozen=True, slots=True)
class Welcome(ControlMessage):
    """Server -> client answer to hello: the user id and the server's limits."""

    TYPE: ClassVar[str] = "welcome"
    user: int
    server_time: float
    """The server clock when it sent welcome, a first guess for clock sync."""
    version: int = PROTOCOL_VERSION
    min_rate: float = MIN_RATE
    max_rate: float = MAX_RATE
    max_streams: int = MAX_STREAMS_PER_USER
    volume: tuple[float, float, float, float, float, float] = _omitted(_DEFAULT_VOLUME_WIRE)
    """The room volume compact updates are quantised in (``protocol.codec.Volume``),
    metres: min x, y, z then max x, y, z. Not sent while it is the default volume."""
    resume: str | None = _omitted(None)
    """For a ``hello.resumable`` client: the token to give in ``hello.resume`` after a
    dropped connection."""
    resumed: bool = _capability()
    """The hello's resume token was honoured: ``user`` is the dropped connection's."""

    def __post_init__(self) -> None:
        check_int("welcome.user", self.user, 0, U16_MAX)
        if not isinstance(self.volume, list | tuple) or len(self.volume) != 6:
            raise bad("welcome.volume", "must be 6 numbers (min x, y, z, max x, y, z)")
        _set(self, "volume", tuple(check_float("welcome.volume", x) for x in self.volume))
        self.room_volume  # noqa: B018 (lo < hi on each axis, else bad-message)
        _set(self, "server_time", check_float("welcome.server_time", self.server_time))
        check_int("welcome.version", self.version, 0, U16_MAX)
        _set(self, "min_rate", check_float("welcome.min_rate", self.min_rate))
        _set(self, "max_rate", check_float("welcome.max_rate", self.max_rate))
        check_int("welcome.max_streams", self.max_streams, 1, U16_MAX + 1)
        check_optional_text("welcome.resume", self.resume)
        check_bool("welcome.resumed", self.resumed)
        if not 0 < self.min_rate <= self.max_rate:
            raise bad("welcome", "needs 0 < min_rate <= max_rate")

    @property
    def room_volume(self) -> Volume:
        """``volume`` as a codec :class:`~protocol.codec.Volume`."""
        lo, hi = self.volume[:3], self.volume[3:]
        return Volume((lo[0], lo[1], lo[2]), (hi[0], hi[1], hi[2]))


@_register
@dataclass(frozen=True, slots=True)
class Join(ControlMessage):
    """Client -> server: enter a room with these streams at this update rate."""

    TYPE: ClassVar[str] = "join"
    room: str
    streams: tuple[str, ...]
    """Stream names: devices ``head``, ``left``, ``right``; objects ``object:NAME``."""
    rate: float | str
    """Requested update rate in Hz, for the snapshots this user receives; or
    ``AUTO_RATE`` ("auto"): the server chooses it, within [``min_rate``,
    ``max_rate``], from what the client's link delivers, and tells it each
    choice with a ``rate`` message (``RateNotice``)."""
    token: str | None = None
    label: str | None = None
    """Name of the motion being played (ground truth for evaluation), if any."""
    sends_velocities: bool = _capability()
    """This client's updates are of the velocity variant (each pose with its
    linear and angular velocity, see ``protocol.poses``); then every update must be."""
    wants_velocities: bool = _capability()
    """Send this client velocity-variant snapshots (streams whose sender reports
    no velocities carry zeros; ``PeerJoined.velocities`` tells which do)."""
    codec: str = _omitted("raw")
    """How this client's updates are coded, one of CODECS: ``raw`` float records
    (``protocol.poses``) or ``compact`` codec update frames (``protocol.codec``,
    quantised in the welcome's volume, delta-coded per stream). Not sent while raw.
    Compact also codes this client's snapshots (``protocol.codec_relay``: delta
    frames against what the server last wrote to it, a key frame at least every
    2 s) and leaves its own streams out of them unless it asks for ``echo``."""
    echo: bool = _capability()
    """Compact snapshots carry this client's own streams too (raw ones always do);
    a benchmark that measures what a full room costs may want it."""
    spectator: bool = _capability()
    """Watch only: the server refuses this client's updates (``stream-not-owned``),
    announces it to nobody (no ``peer_joined`` / ``peer_left`` about it) and sends
    it snapshots and events like any member. Its ``streams`` are nominal."""
    max_rate: float | None = _omitted(None)
    """With ``rate="auto"``: the highest rate the server may choose, Hz (None: the
    server's ``max_rate``). Not sent while None; only allowed with an auto rate."""
    budget_deg: float | None = _omitted(None)
    """An error budget in degrees of visual angle, in (0, 90): the server may send each
    peer's streams at a lower rate than this client's snapshot rate, the lowest whose
    expected interpolation error seen from this client's ``head`` stays within it
    (view-aware rates). None: every peer at the snapshot rate. Not sent while None."""

    @property
    def auto_rate(self) -> bool:
        """Whether the server chooses this client's rate (``rate="auto"``)."""
        return self.rate == AUTO_RATE

    def __post_init__(self) -> None:
        check_text("join.room", self.room)  # empty: the server says bad-room
        if type(self.codec) is not str or self.codec not in CODECS:
            raise bad("join.codec", f"must be one of {', '.join(CODECS)}")
        check_bool("join.sends_velocities", self.sends_velocities)
        check_bool("join.wants_velocities", self.wants_velocities)
        check_bool("join.spectator", self.spectator)
        check_bool("join.echo", self.echo)
        if not isinstance(self.streams, list | tuple):
            raise bad("join.streams", "must be a list of names")
        for name in self.streams:
            check_text("join.streams", name, empty=False)
        _set(self, "streams", tuple(self.streams))
        if self.rate != AUTO_RATE:
            _set(self, "rate", check_float("join.rate", self.rate))
        _set(self, "max_rate", check_optional_float("join.max_rate", self.max_rate))
        if self.max_rate is not None and self.rate != AUTO_RATE:
            raise bad("join.max_rate", 'is only allowed with rate "auto"')
        _set(self, "budget_deg", check_optional_float("join.budget_deg", self.budget_deg))
        if self.budget_deg is not None and not 0.0 < self.budget_deg < 90.0:
            raise bad("join.budget_deg", "must be in (0, 90) degrees")
        check_optional_text("join.token", self.token)
        check_optional_text("join.label", self.label)


@_register
@dataclass(frozen=True, slots=True)
class Joined(ControlMessage):
    """Server -> client: the join succeeded; the stream ids assigned to each name."""

    TYPE: ClassVar[str] = "joined"
    room: str
    streams: dict[str, int]
    """Stream name -> stream id (u16, unique within the room)."""
    rate: float
    """Granted update rate in Hz."""
    objects: dict[str, int] = field(default_factory=dict, metadata={_OMIT_DEFAULT: True})
    """The room's shared objects (``protocol.objects``), name -> stream id; an
    ``object`` message with each one's pose and owner follows. Not sent while empty."""

    def __post_init__(self) -> None:
        check_text("joined.room", self.room, empty=False)
        _set(self, "streams", check_stream_map("joined.streams", self.streams))
        _set(self, "rate", check_float("joined.rate", self.rate))
        _set(self, "objects", check_stream_map("joined.objects", self.objects))


@_register
@dataclass(frozen=True, slots=True)
class PeerJoined(ControlMessage):
    """Server -> client: another user is in the room, with these streams."""

    TYPE: ClassVar[str] = "peer_joined"
    user: int
    streams: dict[str, int]
    label: str | None = None
    velocities: bool = _capability()
    """The user's updates carry velocities (else velocity snapshots hold zeros for it)."""

    def __post_init__(self) -> None:
        check_int("peer_joined.user", self.user, 0, U16_MAX)
        check_bool("peer_joined.velocities", self.velocities)
        _set(self, "streams", check_stream_map("peer_joined.streams", self.streams))
        check_optional_text("peer_joined.label", self.label)


@_register
@dataclass(frozen=True, slots=True)
class PeerLeft(ControlMessage):
    """Server -> client: a user left the room; its streams are gone."""

    TYPE: ClassVar[str] = "peer_left"
    user: int
    reason: str = ""

    def __post_init__(self) -> None:
        check_int("peer_left.user", self.user, 0, U16_MAX)
        check_text("peer_left.reason", self.reason)


@_register
@dataclass(frozen=True, slots=True)
class RateNotice(ControlMessage):
    """Server -> client that joined with ``rate="auto"``: the snapshot rate the server
    chose for it now (Hz). Sent when the choice changes; its playout delay follows."""

    TYPE: ClassVar[str] = "rate"
    rate: float

    def __post_init__(self) -> None:
        _set(self, "rate", check_float("rate.rate", self.rate))


@_register
@dataclass(frozen=True, slots=True)
class PeerStalled(ControlMessage):
    """Server -> client: a user's connection dropped; it may resume (its streams stay,
    frozen at their last pose) or leave (``peer_left``) when its window closes."""

    TYPE: ClassVar[str] = "peer_stalled"
    user: int

    def __post_init__(self) -> None:
        check_int("peer_stalled.user", self.user, 0, U16_MAX)


@_register
@dataclass(frozen=True, slots=True)
class PeerResumed(ControlMessage):
    """Server -> client: a stalled user is back, with the same user and stream ids."""

    TYPE: ClassVar[str] = "peer_resumed"
    user: int

    def __post_init__(self) -> None:
        check_int("peer_resumed.user", self.user, 0, U16_MAX)


@_register
@dataclass(frozen=True, slots=True)
class Ping(ControlMessage):
    """Either way, after welcome: clock sync probe stamped with the sender's clock."""

    TYPE: ClassVar[str] = "ping"
    seq: int
    time: float

    def __post_init__(self) -> None:
        check_int("ping.seq", self.seq, 0, U63_MAX)
        _set(self, "time", check_float("ping.time", self.time))


@_register
@dataclass(frozen=True, slots=True)
class Pong(ControlMessage):
    """Answer to ping: NTP's four timestamps minus the last, which the receiver takes.

    Offset of the answering clock = ((recv_time - ping_time) + (send_time - t3)) / 2
    and round trip = (t3 - ping_time) - (send_time - recv_time), t3 = arrival time.
    """

    TYPE: ClassVar[str] = "pong"
    seq: int
    ping_time: float
    recv_time: float
    send_time: float

    def __post_init__(self) -> None:
        check_int("pong.seq", self.seq, 0, U63_MAX)
        for name in ("ping_time", "recv_time", "send_time"):
            _set(self, name, check_float(f"pong.{name}", getattr(self, name)))

    def offset(self, arrival_time: float) -> float:
        """Answering clock minus pinging clock, given when (pinger's clock) the pong arrived."""
        return ((self.recv_time - self.ping_time) + (self.send_time - arrival_time)) / 2

    def round_trip(self, arrival_time: float) -> float:
        """Network round trip, the answerer's time between receive and send excluded."""
        return (arrival_time - self.ping_time) - (self.send_time - self.recv_time)


@_register
@dataclass(frozen=True, slots=True)
class SetRate(ControlMessage):
    """Client -> server, once joined: change the update rate this user receives."""

    TYPE: ClassVar[str] = "set_rate"
    rate: float

    def __post_init__(self) -> None:
        _set(self, "rate", check_float("set_rate.rate", self.rate))


@_register
@dataclass(frozen=True, slots=True)
class Renew(ControlMessage):
    """Client -> server, once joined: a fresh access token for the same room and user.

    On a server with a secret a connection is closed when its token expires; a
    valid renew moves that deadline to the new token's expiry. A refused renew
    is an ``unauthorized`` error (fatal, 1008), as a bad token at join.
    """

    TYPE: ClassVar[str] = "renew"
    token: str

    def __post_init__(self) -> None:
        check_text("renew.token", self.token, empty=False)


@_register
@dataclass(frozen=True, slots=True)
class UserEvent(ControlMessage):
    """Either way, once joined: a reliable, ordered interaction event.

    A client leaves ``user`` as None (or its own id); the server session stamps
    the sender's id before returning it, and the server relays it with that id.
    """

    TYPE: ClassVar[str] = "event"
    kind: str
    """One of EVENT_KINDS: grab, release, button, scene_step."""
    stream: int | None = None
    """The stream the event is about (the grabbing hand, the pressed controller)."""
    user: int | None = None
    time: float | None = None
    """When it happened, in server time."""
    payload: dict[str, Any] = field(default_factory=dict)
    """Free-form msgpack map, e.g. {"object": "object:drill"}; arrays are stored as tuples."""

    def __post_init__(self) -> None:
        # The type check comes first: an unhashable kind must not reach "in".
        if type(self.kind) is not str or self.kind not in EVENT_KINDS:
            raise bad("event.kind", f"must be one of {', '.join(sorted(EVENT_KINDS))}")
        check_optional_int("event.stream", self.stream, 0, U16_MAX)
        check_optional_int("event.user", self.user, 0, U16_MAX)
        _set(self, "time", check_optional_float("event.time", self.time))
        _set(self, "payload", check_payload("event.payload", self.payload))


@_register
@dataclass(frozen=True, slots=True)
class ErrorMessage(ControlMessage):
    """Either way: tell the peer what it did wrong (codes in ``protocol.errors``).

    ``in_reply_to`` names the type of the message refused ("join", "update", ...);
    a non-fatal error in reply to "join" means the join was refused and the
    client may join again. ``retry_after`` (s, ``server-full``): when to try this
    relay again at the earliest.
    """

    TYPE: ClassVar[str] = "error"
    code: str
    message: str
    fatal: bool = False
    in_reply_to: str | None = None
    retry_after: float | None = _omitted(None)

    def __post_init__(self) -> None:
        check_text("error.code", self.code, max_length=_MAX_CODE_LENGTH, empty=False)
        check_text("error.message", self.message)
        check_bool("error.fatal", self.fatal)
        check_optional_text("error.in_reply_to", self.in_reply_to)
        retry = check_optional_float("error.retry_after", self.retry_after)
        if retry is not None and retry < 0:
            raise bad("error.retry_after", "must not be negative")
        _set(self, "retry_after", retry)

    @classmethod
    def from_code(
        cls,
        code: ErrorCode,
        message: str,
        *,
        in_reply_to: str | None = None,
        retry_after: float | None = None,
    ) -> ErrorMessage:
        """An error message whose fatality follows the code table."""
        return cls(
            code=str(code),
            message=message,
            fatal=code.fatal,
            in_reply_to=in_reply_to,
            retry_after=retry_after,
        )


@_register
@dataclass(frozen=True, slots=True)
class Bye(ControlMessage):
    """Either way: the sender is leaving; the session is over."""

    TYPE: ClassVar[str] = "bye"
    reason: str = ""

    def __post_init__(self) -> None:
        check_text("bye.reason", self.reason)
