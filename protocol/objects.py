"""Shared objects: room-scoped streams whose publisher (owner) can change.

A client creates a named object (``object_create``) with an initial pose. The
object belongs to the room, not to a user: its stream id is unique in the room,
it appears in ``joined.objects`` and in every snapshot like a user's stream,
under the reserved user id :data:`ROOM_USER` whoever publishes it (so a
receiver's buffer for it never changes hands), and by default it outlives its
creator (``keep``). At most one member owns it at a time: only the owner's
updates of its stream are taken.

==================  ====  =====================================================
message             from  meaning
==================  ====  =====================================================
object_create       C     create ``name`` at ``pose``; ``keep`` it after the
                          creator leaves (else removed with it); let others
                          ``steal`` it from an owner; ``hold`` it at once
request_ownership   C     become the owner of object ``stream``: granted when
                          it is unowned (also in flight: a catch), or held by
                          another with ``steal`` asked for, allowed by the
                          object and not locked; ``lock`` keeps it unstealable
                          while held
release             C     give it back, optionally thrown with ``velocity``
                          (m/s) and ``angular`` (rad/s, world frame)
object              S     an object of the room: sent to every member when it
                          is created and to a joiner for each object, with its
                          latest pose, capture time and owner
owner               S     the object's owner changed (or its lock): ordered and
                          reliable, to every member, in the order decided
object_removed      S     the object is gone (its creator left without keep)
==================  ====  =====================================================

A refused request or release is a non-fatal ``ownership-refused`` error; an
update carrying an object stream the sender does not own (it may have lost it
while the update was on its way) loses those entries with a non-fatal
``object-not-owned`` error and keeps the rest. Poses are
``[px, py, pz, qw, qx, qy, qz]`` as in pose updates; times are server time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

from posecast.protocol._validate import (
    U16_MAX,
    bad,
    check_bool,
    check_float,
    check_int,
    check_optional_float,
    check_optional_int,
    check_text,
)
from posecast.protocol.limits import QUAT_NORM_TOLERANCE
from posecast.protocol.messages import _OMIT_DEFAULT, OBJECT_PREFIX, ControlMessage, _register

__all__ = [
    "OBJECT_MESSAGE_TYPES",
    "OWNER_REASONS",
    "ROOM_USER",
    "ObjectCreate",
    "ObjectInfo",
    "ObjectRemoved",
    "Owner",
    "Release",
    "RequestOwnership",
    "pose_tuple",
    "unit_problem",
]

ROOM_USER = U16_MAX
"""The user id of every object stream in snapshots (never given to a connection)."""

OWNER_REASONS = frozenset(
    {"create", "request", "catch", "steal", "lock", "release", "throw", "owner-left"}
)
"""Values of ``Owner.reason``: why the owner (or the lock) changed."""

Pose7 = tuple[float, float, float, float, float, float, float]
Vec3 = tuple[float, float, float]


def pose_tuple(where: str, value: object) -> Pose7:
    """Seven finite numbers ``[px, py, pz, qw, qx, qy, qz]`` (the norm is the session's)."""
    if not isinstance(value, list | tuple) or len(value) != 7:
        raise bad(where, "must be 7 numbers (px, py, pz, qw, qx, qy, qz)")
    p = tuple(check_float(where, x) for x in value)
    return (p[0], p[1], p[2], p[3], p[4], p[5], p[6])


def _vector(where: str, value: object) -> Vec3 | None:
    if value is None:
        return None
    if not isinstance(value, list | tuple) or len(value) != 3:
        raise bad(where, "must be 3 numbers or absent")
    v = tuple(check_float(where, x) for x in value)
    return (v[0], v[1], v[2])


def _check_object_name(where: str, name: object) -> str:
    text = check_text(where, name, empty=False)
    if not text.startswith(OBJECT_PREFIX):
        raise bad(where, f"must start with {OBJECT_PREFIX!r}")
    return text


def unit_problem(pose: Pose7) -> str | None:
    """Why ``pose``'s quaternion is no rotation (its norm off 1 by over
    ``QUAT_NORM_TOLERANCE``, the bound of pose updates), or None."""
    norm = math.sqrt(sum(x * x for x in pose[3:]))
    if abs(norm - 1.0) > QUAT_NORM_TOLERANCE:
        return f"quaternion norm {norm:.4g} is not 1"
    return None


@_register
@dataclass(frozen=True, slots=True)
class ObjectCreate(ControlMessage):
    """Client -> server, once joined: create a room object at ``pose``."""

    TYPE: ClassVar[str] = "object_create"
    name: str
    """``object:NAME``, unique in the room."""
    pose: Pose7
    keep: bool = True
    """The object stays when its creator leaves (else it is removed with it)."""
    steal: bool = field(default=False, metadata={_OMIT_DEFAULT: True})
    """Another member may take it from its owner (unless the owner locked it)."""
    hold: bool = field(default=False, metadata={_OMIT_DEFAULT: True})
    """The creator owns it at once."""
    time: float | None = field(default=None, metadata={_OMIT_DEFAULT: True})
    """Capture time (server clock) of ``pose``; absent: when the server receives it.
    A creator that holds it and goes on publishing should give it, so that its
    next keyframes come after the first one."""

    def __post_init__(self) -> None:
        _check_object_name("object_create.name", self.name)
        object.__setattr__(self, "time", check_optional_float("object_create.time", self.time))
        object.__setattr__(self, "pose", pose_tuple("object_create.pose", self.pose))
        check_bool("object_create.keep", self.keep)
        check_bool("object_create.steal", self.steal)
        check_bool("object_create.hold", self.hold)


@_register
@dataclass(frozen=True, slots=True)
class RequestOwnership(ControlMessage):
    """Client -> server, once joined: make me the owner of object ``stream``."""

    TYPE: ClassVar[str] = "request_ownership"
    stream: int
    steal: bool = field(default=False, metadata={_OMIT_DEFAULT: True})
    """Take it even from another owner (if the object allows it and it is not locked)."""
    lock: bool = field(default=False, metadata={_OMIT_DEFAULT: True})
    """While I hold it, nobody may steal it."""

    def __post_init__(self) -> None:
        check_int("request_ownership.stream", self.stream, 0, U16_MAX)
        check_bool("request_ownership.steal", self.steal)
        check_bool("request_ownership.lock", self.lock)


@_register
@dataclass(frozen=True, slots=True)
class Release(ControlMessage):
    """Client -> server, once joined: I no longer own object ``stream``.

    With ``velocity`` it is thrown: the server moves it ballistically from its
    last pose (gravity along -y, the room's floor) until someone takes it.
    """

    TYPE: ClassVar[str] = "release"
    stream: int
    velocity: Vec3 | None = field(default=None, metadata={_OMIT_DEFAULT: True})
    angular: Vec3 | None = field(default=None, metadata={_OMIT_DEFAULT: True})

    def __post_init__(self) -> None:
        check_int("release.stream", self.stream, 0, U16_MAX)
        object.__setattr__(self, "velocity", _vector("release.velocity", self.velocity))
        object.__setattr__(self, "angular", _vector("release.angular", self.angular))


@_register
@dataclass(frozen=True, slots=True)
class ObjectInfo(ControlMessage):
    """Server -> client: an object of the room, its latest pose and its owner."""

    TYPE: ClassVar[str] = "object"
    name: str
    stream: int
    pose: Pose7
    time: float
    """Capture time (server clock) of ``pose``."""
    creator: int
    owner: int | None = None
    keep: bool = True
    steal: bool = field(default=False, metadata={_OMIT_DEFAULT: True})
    locked: bool = field(default=False, metadata={_OMIT_DEFAULT: True})

    def __post_init__(self) -> None:
        _check_object_name("object.name", self.name)
        check_int("object.stream", self.stream, 0, U16_MAX)
        object.__setattr__(self, "pose", pose_tuple("object.pose", self.pose))
        object.__setattr__(self, "time", check_float("object.time", self.time))
        check_int("object.creator", self.creator, 0, U16_MAX)
        check_optional_int("object.owner", self.owner, 0, U16_MAX)
        check_bool("object.keep", self.keep)
        check_bool("object.steal", self.steal)
        check_bool("object.locked", self.locked)


@_register
@dataclass(frozen=True, slots=True)
class Owner(ControlMessage):
    """Server -> client: object ``stream`` has a new owner (None: nobody), and why."""

    TYPE: ClassVar[str] = "owner"
    stream: int
    owner: int | None
    previous: int | None
    reason: str
    """One of OWNER_REASONS."""
    time: float
    """Server time of the change."""
    locked: bool = field(default=False, metadata={_OMIT_DEFAULT: True})
    velocity: Vec3 | None = field(default=None, metadata={_OMIT_DEFAULT: True})
    """A throw's release velocity (m/s), angular rad/s beside it."""
    angular: Vec3 | None = field(default=None, metadata={_OMIT_DEFAULT: True})

    def __post_init__(self) -> None:
        check_int("owner.stream", self.stream, 0, U16_MAX)
        check_optional_int("owner.owner", self.owner, 0, U16_MAX)
        check_optional_int("owner.previous", self.previous, 0, U16_MAX)
        if type(self.reason) is not str or self.reason not in OWNER_REASONS:
            raise bad("owner.reason", f"must be one of {', '.join(sorted(OWNER_REASONS))}")
        object.__setattr__(self, "time", check_float("owner.time", self.time))
        check_bool("owner.locked", self.locked)
        object.__setattr__(self, "velocity", _vector("owner.velocity", self.velocity))
        object.__setattr__(self, "angular", _vector("owner.angular", self.angular))


@_register
@dataclass(frozen=True, slots=True)
class ObjectRemoved(ControlMessage):
    """Server -> client: object ``stream`` is gone (``reason``: why)."""

    TYPE: ClassVar[str] = "object_removed"
    stream: int
    reason: str = ""

    def __post_init__(self) -> None:
        check_int("object_removed.stream", self.stream, 0, U16_MAX)
        check_text("object_removed.reason", self.reason)


OBJECT_MESSAGE_TYPES: tuple[type[ControlMessage], ...] = (
    ObjectCreate,
    RequestOwnership,
    Release,
    ObjectInfo,
    Owner,
    ObjectRemoved,
)
"""The shared-object messages (``protocol.wire`` decodes them like the others)."""
