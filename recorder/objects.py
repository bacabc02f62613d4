"""Shared objects in a recording: what was created, who held it, how it moved.

The relay (``server/objects.py``) records an object's life on the ``events``
topic (records with ``kind``, ``user``, ``stream``, ``time`` and ``payload``):

==============  ========================  ==========================================
kind            user                      payload
==============  ========================  ==========================================
object_create   the creator               ``object`` (name), ``pose``, ``keep``
owner           the new owner, or null    ``object``, ``previous``, ``reason``,
                                          ``locked``, ``velocity``, ``angular``
object_remove   the creator               ``object``, ``reason``
==============  ========================  ==========================================

and its motion on the ``poses`` topic: an owner's updates carry the object's
stream id beside the owner's own streams, with the capture times the owner
sent (not shifted as the relay stores them), and the relay's keyframes of a
thrown object in flight are updates of user :data:`ROOM_USER` (65535) with
velocities.

:func:`build_tracks` turns those into one :class:`ObjectTrack` per object: its
keyframes in arrival order (the create pose first), who published each, and
the times the room stored them under -- each new owner's keyframes shifted as
the relay shifts them (its first one at least 1 ms after the object's newest,
``MIN_STEP``), and keyframes the relay would not store (not newer than its
newest) left out and counted. :meth:`ObjectTrack.stream` is the object as
one stream of user ``ROOM_USER`` named by the object, which is how the room
relayed it; :func:`split_objects` takes the object keyframes out of the users'
streams and gives these instead.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from posecast.recorder.streams import StreamData, UserInfo

__all__ = [
    "MIN_STEP",
    "OBJECT_EVENT_KINDS",
    "RESTED",
    "ROOM_USER",
    "ObjectAction",
    "ObjectTrack",
    "OwnerChange",
    "build_tracks",
    "format_objects",
    "object_actions",
    "objects_info",
    "owner_keyframes",
    "split_objects",
]

#: The user id of object streams in snapshots and of the relay's flight keyframes
#: (``protocol.objects.ROOM_USER``).
ROOM_USER = 0xFFFF
#: A new owner's first keyframe is stored at least this long after the object's
#: newest (``server.objects.MIN_STEP``).
MIN_STEP = 1e-3
#: A flight starts from the object's newest keyframe, or from the throw when that
#: keyframe is older than this (``server.objects.RESTED``).
RESTED = 0.1
OBJECT_EVENT_KINDS = frozenset({"object_create", "owner", "object_remove"})

F64 = NDArray[np.float64]
Vec3 = tuple[float, float, float]


def _vec(value: object) -> Vec3 | None:
    if not isinstance(value, list | tuple) or len(value) != 3:
        return None
    try:
        x, y, z = (float(v) for v in value)
    except (TypeError, ValueError):
        return None
    return (x, y, z)


def _user(value: object) -> int | None:
    return value if isinstance(value, int) and not isinstance(value, bool) else None


@dataclass(frozen=True)
class OwnerChange:
    """One ``owner`` record: object ``stream`` went from ``previous`` to ``owner``."""

    time: float
    """Server time of the change."""
    object: str
    stream: int
    owner: int | None
    previous: int | None
    reason: str
    """``create``, ``request``, ``catch``, ``steal``, ``lock``, ``release``,
    ``throw`` or ``owner-left``."""
    locked: bool = False
    velocity: Vec3 | None = None
    """A throw's release velocity (m/s)."""
    angular: Vec3 | None = None
    """A throw's angular velocity (rad/s)."""

    def as_dict(self) -> dict[str, Any]:
        return {
            "time": self.time,
            "object": self.object,
            "stream": self.stream,
            "owner": self.owner,
            "previous": self.previous,
            "reason": self.reason,
            "locked": self.locked,
            "velocity": None if self.velocity is None else list(self.velocity),
            "angular": None if self.angular is None else list(self.angular),
        }


@dataclass(frozen=True, eq=False)
class ObjectTrack:
    """One object of a recording: its records and its keyframes in arrival order."""

    name: str
    stream: int
    creator: int | None
    keep: bool
    created: float
    """Server time of its ``object_create`` record (its first keyframe's time)."""
    removed: float | None
    removed_reason: str | None
    changes: tuple[OwnerChange, ...]
    publisher: NDArray[np.uint16]
    """Who published each keyframe: the creator (the create pose, first), an owner,
    or ``ROOM_USER`` (the relay, in flight)."""
    flight: NDArray[np.bool_]
    """True for the relay's flight keyframes."""
    captures: F64
    """Capture times as recorded (an owner's own estimate of server time)."""
    times: F64
    """The times the room stored the keyframes under (strictly increasing)."""
    arrival: F64
    poses: NDArray[np.float32]
    velocities: NDArray[np.float32]
    """``(K, 6)``: a flight keyframe's velocity; NaN where a keyframe carried none."""
    stale: int = 0
    """Recorded keyframes of owners that the room did not store (not newer than
    its newest keyframe of the object)."""

    def __len__(self) -> int:
        return len(self.times)

    @property
    def flight_keyframes(self) -> int:
        return int(np.count_nonzero(self.flight))

    @property
    def holders(self) -> list[int]:
        """Every user that held it, in the order they first took it."""
        out: list[int] = []
        for c in self.changes:
            if c.owner is not None and c.owner not in out:
                out.append(c.owner)
        return out

    def stream_data(self) -> StreamData:
        """The object as the room relayed it: one stream of ``ROOM_USER`` named by it."""
        vel = None if np.isnan(self.velocities).all() else self.velocities
        return StreamData(
            user=ROOM_USER,
            stream=self.stream,
            name=self.name,
            user_name="room",
            times=self.times,
            arrival=self.arrival,
            poses=self.poses,
            velocities=vel,
        )


@dataclass
class _Building:
    name: str
    stream: int
    creator: int | None
    keep: bool
    created: float
    pose: tuple[float, ...]
    removed: float | None = None
    removed_reason: str | None = None
    changes: list[OwnerChange] = field(default_factory=list)
    # (arrival, capture, publisher, flight, pose, velocity) of each recorded keyframe
    rows: list[tuple[float, float, int, bool, NDArray[np.float32], NDArray[np.float32]]] = field(
        default_factory=list
    )


def _pose7(value: object) -> tuple[float, ...] | None:
    if not isinstance(value, list | tuple) or len(value) != 7:
        return None
    try:
        return tuple(float(v) for v in value)
    except (TypeError, ValueError):
        return None


def _objects_from_events(events: Iterable[Mapping[str, Any]]) -> list[_Building]:
    """Objects with their changes, in creation order; malformed records are skipped."""
    out: list[_Building] = []
    live: dict[int, _Building] = {}
    for d in events:
        kind, stream, time = d.get("kind"), _user(d.get("stream")), d.get("time")
        payload = d.get("payload")
        if kind not in OBJECT_EVENT_KINDS or stream is None or not isinstance(payload, dict):
            continue
        if not isinstance(time, int | float) or not math.isfinite(time):
            continue
        name = str(payload.get("object", f"object:{stream}"))
        if kind == "object_create":
            pose = _pose7(payload.get("pose"))
            if pose is None:
                continue
            obj = _Building(
                name,
                stream,
                _user(d.get("user")),
                bool(payload.get("keep", True)),
                float(time),
                pose,
            )
            out.append(obj)
            live[stream] = obj
            continue
        found = live.get(stream)
        if found is None:
            continue
        if kind == "object_remove":
            found.removed, found.removed_reason = float(time), str(payload.get("reason", ""))
            del live[stream]
        else:
            found.changes.append(
                OwnerChange(
                    time=float(time),
                    object=found.name,
                    stream=stream,
                    owner=_user(d.get("user")),
                    previous=_user(payload.get("previous")),
                    reason=str(payload.get("reason", "")),
                    locked=bool(payload.get("locked", False)),
                    velocity=_vec(payload.get("velocity")),
                    angular=_vec(payload.get("angular")),
                )
            )
    return out


def _is_object_piece(key: tuple[int, int], users: Mapping[int, UserInfo]) -> bool:
    """Keyframes of ``(user, stream)`` are an object's: the relay's, or a stream the
    user did not join with (its streams are named in its presence records)."""
    user, sid = key
    info = users.get(user)
    return user == ROOM_USER or info is None or sid not in info.streams


def _room_times(obj: _Building, order: list[int]) -> tuple[F64, list[int], int]:
    """Stored times of the rows in ``order`` as the relay stores them; rows kept; stale."""
    rows, changes = obj.rows, obj.changes
    last = obj.created
    fresh, offset, ci, stale = False, 0.0, 0, 0
    times: list[float] = []
    kept: list[int] = []
    for k in order:
        arrival, capture, publisher, flight, _p, _v = rows[k]
        # Changes before this keyframe; at one clock reading, a grant to its publisher.
        while ci < len(changes) and (
            changes[ci].time < arrival
            or (changes[ci].time == arrival and changes[ci].owner == publisher)
        ):
            if changes[ci].reason != "lock":
                fresh = True
            ci += 1
        t = capture
        if not flight:
            if fresh:
                fresh, offset = False, max(0.0, last + MIN_STEP - capture)
            t = capture + offset
        if t <= last:
            stale += 1
            continue
        last = t
        times.append(t)
        kept.append(k)
    return np.asarray(times, dtype=np.float64), kept, stale


def _track(obj: _Building) -> ObjectTrack:
    order = sorted(range(len(obj.rows)), key=lambda k: obj.rows[k][0])
    times, kept, stale = _room_times(obj, order)
    rows = [obj.rows[k] for k in kept]
    first_pose = np.asarray(obj.pose, dtype=np.float32)
    nan6 = np.full(6, np.nan, dtype=np.float32)
    return ObjectTrack(
        name=obj.name,
        stream=obj.stream,
        creator=obj.creator,
        keep=obj.keep,
        created=obj.created,
        removed=obj.removed,
        removed_reason=obj.removed_reason,
        changes=tuple(obj.changes),
        publisher=np.array(
            [ROOM_USER if obj.creator is None else obj.creator] + [r[2] for r in rows],
            dtype=np.uint16,
        ),
        flight=np.array([False] + [r[3] for r in rows], dtype=bool),
        captures=np.array([obj.created] + [r[1] for r in rows], dtype=np.float64),
        times=np.concatenate([[obj.created], times]),
        arrival=np.array([obj.created] + [r[0] for r in rows], dtype=np.float64),
        poses=np.stack([first_pose] + [r[4] for r in rows]).astype(np.float32),
        velocities=np.stack([nan6] + [r[5] for r in rows]).astype(np.float32),
        stale=stale,
    )


def build_tracks(
    events: Iterable[Mapping[str, Any]],
    pieces: Mapping[tuple[int, int], StreamData],
    users: Mapping[int, UserInfo],
) -> tuple[list[ObjectTrack], set[tuple[int, int]]]:
    """Every object of a recording and the ``(user, stream)`` pieces its keyframes came in.

    ``events``: the ``events`` records (dicts) in file order; ``pieces``: the
    recording's streams by ``(user, stream)`` (:meth:`SessionReader.load_streams`);
    ``users``: from the presence records. A keyframe belongs to the object of its
    stream id that existed when it arrived.
    """
    objects = _objects_from_events(events)
    by_stream: dict[int, list[_Building]] = {}
    for obj in objects:
        by_stream.setdefault(obj.stream, []).append(obj)
    used: set[tuple[int, int]] = set()
    for key, s in pieces.items():
        candidates = by_stream.get(key[1])
        if not candidates or not _is_object_piece(key, users):
            continue
        used.add(key)
        vel = s.velocities
        for k in range(len(s)):
            a = float(s.arrival[k])
            obj = next(
                (o for o in reversed(candidates) if o.created <= a),
                candidates[0],
            )
            v = np.full(6, np.nan, np.float32) if vel is None else vel[k]
            obj.rows.append((a, float(s.times[k]), key[0], key[0] == ROOM_USER, s.poses[k], v))
    return [_track(o) for o in objects], used


def split_objects(
    events: Iterable[Mapping[str, Any]],
    pieces: Mapping[tuple[int, int], StreamData],
    users: Mapping[int, UserInfo],
) -> tuple[dict[tuple[int, int], StreamData], list[ObjectTrack]]:
    """The users' own streams (object keyframes taken out) and the objects' tracks."""
    tracks, used = build_tracks(events, pieces, users)
    return {k: s for k, s in pieces.items() if k not in used}, tracks


def objects_info(tracks: Iterable[ObjectTrack]) -> list[dict[str, Any]]:
    """The ``objects`` entry of :func:`recorder.info`."""
    out = []
    for t in tracks:
        reasons: dict[str, int] = {}
        for c in t.changes:
            reasons[c.reason] = reasons.get(c.reason, 0) + 1
        out.append(
            {
                "name": t.name,
                "stream": t.stream,
                "creator": t.creator,
                "keep": t.keep,
                "created": t.created,
                "removed": t.removed,
                "removed_reason": t.removed_reason,
                "owner_changes": len(t.changes),
                "reasons": dict(sorted(reasons.items())),
                "holders": t.holders,
                "keyframes": len(t),
                "flight_keyframes": t.flight_keyframes,
                "stale_keyframes": t.stale,
            }
        )
    return out


def format_objects(objects: list[dict[str, Any]]) -> list[str]:
    """Lines of ``posecast info`` for the objects (none without objects)."""
    if not objects:
        return []
    lines = [f"  objects: {len(objects)}"]
    for o in objects:
        creator = "-" if o["creator"] is None else o["creator"]
        gone = f", removed ({o['removed_reason']})" if o["removed"] is not None else ""
        holders = ", ".join(str(h) for h in o["holders"]) or "nobody"
        reasons = ", ".join(f"{k} {v}" for k, v in o["reasons"].items())
        lines.append(
            f"    {o['stream']:>5} {o['name']} creator {creator}"
            f" keep {'yes' if o['keep'] else 'no'}{gone}"
        )
        lines.append(
            f"          {o['owner_changes']} owner changes ({reasons or 'none'}),"
            f" held by {holders}; {o['keyframes']} keyframes,"
            f" {o['flight_keyframes']} in flight"
        )
    return lines


@dataclass(frozen=True)
class ObjectAction:
    """What a replaying client sends to reproduce a recorded object change.

    ``create``: ``object_create`` (``hold`` when the creator held it at once;
    ``steal`` when the recording shows a steal of it: the record does not keep
    the flag). ``request``: ``request_ownership`` (with ``steal`` and ``lock`` as
    recorded; a lock change is a request by the owner). ``release``: ``release``,
    with the throw's velocities if it was thrown. ``previous`` is the recorded
    owner before the change: the replay waits until the live object has that
    owner (mapped to the live user) before it sends the action.
    """

    time: float
    """Recorded server time of the change."""
    kind: str
    name: str
    user: int
    """The recorded user that sends it."""
    previous: int | None = None
    pose: tuple[float, ...] | None = None
    keep: bool = True
    steal: bool = False
    hold: bool = False
    lock: bool = False
    velocity: Vec3 | None = None
    angular: Vec3 | None = None

    @property
    def grant(self) -> bool:
        """The sender becomes the owner (or creates): it goes before an update sent at
        the same time, which may carry the object; a release goes after one."""
        return self.kind != "release"


def _change_action(c: OwnerChange) -> ObjectAction | None:
    if c.reason in ("request", "catch", "steal", "lock") and c.owner is not None:
        previous = c.owner if c.reason == "lock" else c.previous
        return ObjectAction(
            c.time,
            "request",
            c.object,
            c.owner,
            previous,
            steal=c.reason == "steal",
            lock=c.locked,
        )
    if c.reason in ("release", "throw") and c.previous is not None:
        return ObjectAction(
            c.time,
            "release",
            c.object,
            c.previous,
            c.previous,
            velocity=c.velocity,
            angular=c.angular,
        )
    return None  # create (a create with hold) and owner-left (the owner leaves)


def object_actions(tracks: Iterable[ObjectTrack]) -> dict[int, list[ObjectAction]]:
    """Each recorded user's object actions, in time order (see :class:`ObjectAction`)."""
    out: dict[int, list[ObjectAction]] = {}
    for t in tracks:
        if t.creator is not None and t.creator != ROOM_USER:
            first = t.changes[0] if t.changes else None
            hold = first is not None and first.reason == "create" and first.time == t.created
            out.setdefault(t.creator, []).append(
                ObjectAction(
                    t.created,
                    "create",
                    t.name,
                    t.creator,
                    pose=tuple(float(x) for x in t.poses[0]),
                    keep=t.keep,
                    steal=any(c.reason == "steal" for c in t.changes),
                    hold=hold,
                )
            )
        for c in t.changes:
            action = _change_action(c)
            if action is not None:
                out.setdefault(action.user, []).append(action)
    for actions in out.values():
        actions.sort(key=lambda a: a.time)
    return out


def owner_keyframes(track: ObjectTrack, user: int) -> StreamData | None:
    """The keyframes of ``track`` that ``user`` published as its owner, as recorded
    (its own capture times), or None if it published none."""
    idx = np.flatnonzero((track.publisher == user) & ~track.flight)
    idx = idx[idx > 0]  # the first keyframe is the create pose, not an update
    if not idx.size:
        return None
    vel = track.velocities[idx]
    return StreamData(
        user=user,
        stream=track.stream,
        name=track.name,
        user_name=None,
        times=track.captures[idx],
        arrival=track.arrival[idx],
        poses=track.poses[idx],
        velocities=None if np.isnan(vel).any() else vel,
    )
