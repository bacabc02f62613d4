"""Shared objects: the relay's ownership rules, thrown flights and their records.

A room object (``protocol.objects``) is a stream of the room, not of a user: it
is published under :data:`~protocol.objects.ROOM_USER` by whoever owns it, and
by the server itself while it flies. The rules, applied in the order requests
arrive (one event loop: no two grants race):

==================  ==========================================================
request             the relay ...
==================  ==========================================================
object_create       refuses (``ownership-refused``) a name the room has or
                    over ``max_objects``, a pose outside the volume
                    (``bad-pose``, also for a ``time`` over the capture age
                    or ahead limits); else allocates a stream, stores the
                    pose as its first keyframe (at ``time``, else now), tells
                    every member
                    (``object``), and with ``hold`` makes the creator owner
request_ownership   grants it (``owner`` to every member, the requester
                    included) when the object is unowned (reason ``request``;
                    ``catch`` if it was flying), or held by another while the
                    request asks to ``steal``, the object allows it and the
                    owner did not lock it (``steal``); the owner asking again
                    changes its lock (``lock``); else ``ownership-refused``
release             by the owner: unowned, at rest at its last pose
                    (``release``) or, with a velocity, flying (``throw``);
                    by anyone else: ``ownership-refused``
owner leaves        when it leaves for good (bye, or its resume window over),
                    its objects are released (``owner-left``); a parked owner
                    keeps them; an object of its creation without ``keep`` is
                    removed (``object_removed``, reason ``creator-left``)
==================  ==========================================================

Refusals for contention (held, locked, not yours) are not charged to the
misbehaviour budget: two users reaching for one object is normal. A request
about no object is.

**Flight.** A thrown object is moved by the server, not by each receiver: one
authority, so every receiver, the recording and a replay see the same motion,
and a late joiner sees it mid-air. From its last keyframe (time ``t0``, pose,
the release velocity ``v`` and angular velocity ``w``) the position follows
``p0 + v (t - t0) - g (t - t0)^2 / 2`` (gravity 9.81 m/s^2 along -y; ``t0`` is
the release time instead if that keyframe is over 0.1 s old) and the
rotation turns at ``w`` until the object reaches the floor (y = 0, or the
volume's floor if higher), where it rests. The relay stores a keyframe of it
at each tick of the room (each subscriber's own rate), with its velocity, and
records it as a pose update of ``ROOM_USER``. The cost is the bytes of those
keyframes, as if a user held it.

**Clocks at a handover.** Keyframe times are capture times in server time,
each publisher's own estimate: a new owner's estimate may sit a few ms off the
previous owner's (or off the server's flight keyframes). The relay keeps an
object's keyframe times increasing across a change of owner: the new owner's
keyframes are shifted, for as long as it owns the object, by the smallest
offset (never negative) that puts its first one at least 1 ms after the
object's last keyframe. A new owner whose clock runs ahead leaves a longer
interval between two keyframes, which interpolation bridges; one behind would
otherwise have its first keyframes dropped as stale.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from posecast.protocol import (
    ROOM_USER,
    ErrorCode,
    ObjectCreate,
    ObjectInfo,
    ObjectRemoved,
    Owner,
    PoseUpdate,
    Release,
    RequestOwnership,
)
from posecast.server.shared import (
    GRAVITY,
    POSE_STRUCT,
    RESTED,
    VELOCITY_STRUCT,
    Flight,
    RoomObject,
    Vec3,
    pose_bytes,
)

if TYPE_CHECKING:
    from posecast.server.peer import Peer
    from posecast.server.ports import Relay
    from posecast.server.room import Room

__all__ = ["GRAVITY", "Flight", "RoomObject", "handle", "introduce", "owner_left", "restore"]


def _info(room: Room, obj: RoomObject) -> ObjectInfo:
    capture, raw = room.stream_pose(obj.stream)
    pose = POSE_STRUCT.unpack(raw)
    # float32 on the wire of snapshots; the message carries the same values.
    return ObjectInfo(
        name=obj.name,
        stream=obj.stream,
        pose=pose,
        time=capture,
        creator=obj.creator,
        owner=obj.owner,
        keep=obj.keep,
        steal=obj.steal,
        locked=obj.locked,
    )


def joined_objects(room: Room) -> dict[str, int]:
    """``joined.objects``: the room's objects, name -> stream id."""
    return {obj.name: obj.stream for obj in room.objects.values()}


def introduce(core: Relay, peer: Peer, room: Room) -> None:
    """A joiner learns every object of ``room``: its pose, time and owner."""
    peer.session.objects = room.objects
    for obj in room.objects.values():
        core.send(peer, _info(room, obj))


def restore(core: Relay, peer: Peer, room: Room) -> None:
    """A resumed member gets back the objects it owned (and learns them all anew)."""
    for obj in room.objects.values():
        if obj.owner == peer.user:
            peer.session.hold(obj.stream)
    introduce(core, peer, room)


def handle(
    core: Relay, peer: Peer, event: ObjectCreate | RequestOwnership | Release, now: float
) -> None:
    """Apply one shared-object request of ``peer``."""
    room, user = peer.room, peer.user
    if room is None or user is None or not core.admit_update(peer, now):
        return
    if core.is_spectator(user):
        _refuse(core, peer, event, "spectators own nothing", now, charge=True)
    elif isinstance(event, ObjectCreate):
        _create(core, peer, room, user, event, now)
    else:
        obj = room.objects.get(event.stream)
        if obj is None:
            _refuse(core, peer, event, f"no object with stream {event.stream}", now, charge=True)
        elif isinstance(event, RequestOwnership):
            _request(core, peer, room, user, obj, event, now)
        else:
            _release(core, peer, room, user, obj, event, now)


def _refuse(
    core: Relay,
    peer: Peer,
    event: ObjectCreate | RequestOwnership | Release,
    message: str,
    now: float,
    charge: bool = False,
) -> None:
    core.refuse(peer, ErrorCode.OWNERSHIP_REFUSED, message, event.TYPE, now, charge)


def _create(
    core: Relay, peer: Peer, room: Room, user: int, event: ObjectCreate, now: float
) -> None:
    if any(obj.name == event.name for obj in room.objects.values()):
        _refuse(core, peer, event, f"{event.name} exists in this room", now)
        return
    if len(room.objects) >= core.config.max_objects:
        _refuse(core, peer, event, f"room holds {core.config.max_objects} objects", now)
        return
    box = zip(core.volume.lo, event.pose[:3], core.volume.hi, strict=True)
    if not all(lo <= x <= hi for lo, x, hi in box):
        core.refuse(
            peer, ErrorCode.BAD_POSE, "object position outside the room volume", event.TYPE, now
        )
        return
    capture = now if event.time is None else event.time
    cfg = core.config
    if not now - cfg.max_capture_age <= capture <= now + cfg.max_capture_ahead:
        core.refuse(
            peer,
            ErrorCode.BAD_POSE,
            f"object_create.time {capture - now:+.3f} s from now",
            event.TYPE,
            now,
        )
        return
    obj = RoomObject(event.name, room.stream_ids.take(), user, event.keep, event.steal)
    room.objects[obj.stream] = obj
    room.store(obj.stream, ROOM_USER, capture, pose_bytes(event.pose))
    info = _info(room, obj)
    for member in list(room.members.values()):
        core.to_member(member, info)
    _record(room, "object_create", user, obj, now, pose=list(event.pose), keep=obj.keep)
    if event.hold:
        _change(core, room, obj, user, "create", now)


def _request(
    core: Relay,
    peer: Peer,
    room: Room,
    user: int,
    obj: RoomObject,
    event: RequestOwnership,
    now: float,
) -> None:
    if obj.owner == user:
        if obj.locked != event.lock:
            obj.locked = event.lock
            _announce(core, room, obj, user, user, "lock", now)
        return
    if obj.owner is None:
        reason = "catch" if obj.flight is not None else "request"
    elif event.steal and obj.steal and not obj.locked:
        reason = "steal"
    else:
        if obj.locked:
            why = "locked"
        elif obj.steal:
            why = "held (ask with steal)"
        else:
            why = "held (not stealable)"
        _refuse(core, peer, event, f"{obj.name} is {why} by user {obj.owner}", now)
        return
    _change(core, room, obj, user, reason, now, lock=event.lock)


def _release(
    core: Relay, peer: Peer, room: Room, user: int, obj: RoomObject, event: Release, now: float
) -> None:
    if obj.owner != user:
        _refuse(core, peer, event, f"{obj.name} is not held by user {user}", now)
        return
    thrown = event.velocity is not None and any(event.velocity)
    _change(core, room, obj, None, "throw" if thrown else "release", now)
    if thrown:
        assert event.velocity is not None
        capture, raw = room.stream_pose(obj.stream)
        # From its last keyframe; one over RESTED old means it lay still until now.
        start = capture if now - capture < RESTED else now
        floor = max(0.0, core.volume.lo[1])
        obj.flight = Flight(
            start, POSE_STRUCT.unpack(raw), event.velocity, event.angular or (0.0, 0.0, 0.0), floor
        )
        spin = event.angular
        _announce(core, room, obj, None, user, "throw", now, velocity=event.velocity, angular=spin)
    else:
        _announce(core, room, obj, None, user, "release", now)


def _change(
    core: Relay,
    room: Room,
    obj: RoomObject,
    owner: int | None,
    reason: str,
    now: float,
    lock: bool = False,
) -> None:
    """Move ``obj`` to ``owner``: the sessions' rights; told (unless a release) and recorded."""
    previous = obj.owner
    held_by = None if previous is None else core.connected(previous)
    if held_by is not None:
        held_by.session.let_go(obj.stream)
    obj.give(owner)
    obj.locked = lock and owner is not None
    if owner is not None:
        taker = core.connected(owner)
        if taker is not None:
            taker.session.hold(obj.stream)
        _announce(core, room, obj, owner, previous, reason, now)


def _announce(
    core: Relay,
    room: Room,
    obj: RoomObject,
    owner: int | None,
    previous: int | None,
    reason: str,
    now: float,
    velocity: Vec3 | None = None,
    angular: Vec3 | None = None,
) -> None:
    """Tell every member (the new owner too) and record the change."""
    message = Owner(
        stream=obj.stream,
        owner=owner,
        previous=previous,
        reason=reason,
        time=now,
        locked=obj.locked,
        velocity=velocity,
        angular=angular,
    )
    for member in list(room.members.values()):
        core.to_member(member, message)
    _record(
        room,
        "owner",
        owner,
        obj,
        now,
        previous=previous,
        reason=reason,
        locked=obj.locked,
        velocity=None if velocity is None else list(velocity),
        angular=None if angular is None else list(angular),
    )


def owner_left(core: Relay, room: Room, user: int, now: float) -> None:
    """``user`` leaves ``room`` for good: release what it holds, remove what dies with it."""
    for obj in list(room.objects.values()):
        if obj.creator == user and not obj.keep:
            _remove(core, room, obj, "creator-left", now)
        elif obj.owner == user:
            obj.give(None)
            _announce(core, room, obj, None, user, "owner-left", now)


def _remove(core: Relay, room: Room, obj: RoomObject, reason: str, now: float) -> None:
    held_by = None if obj.owner is None else core.connected(obj.owner)
    if held_by is not None:
        held_by.session.let_go(obj.stream)
    del room.objects[obj.stream]
    room.drop_stream(obj.stream)
    message = ObjectRemoved(stream=obj.stream, reason=reason)
    for member in list(room.members.values()):
        core.to_member(member, message)
    _record(room, "object_remove", obj.creator, obj, now, reason=reason)


def _record(
    room: Room, kind: str, user: int | None, obj: RoomObject, now: float, **payload: object
) -> None:
    """An object's change, on the recording's events topic (``kind`` says which)."""
    if room.recorded:
        room.record(
            "event",
            {
                "kind": kind,
                "user": user,
                "stream": obj.stream,
                "time": now,
                "payload": {"object": obj.name, **payload},
            },
            now,
        )


def fly(room: Room, now: float) -> None:
    """Store a keyframe of every flying object of ``room`` at ``now`` (its tick)."""
    for obj in room.objects.values():
        flight = obj.flight
        if flight is None or now <= room.stream_pose(obj.stream)[0]:
            continue
        pose, velocity, landed = flight.at(now)
        pose_raw, vel_raw = pose_bytes(pose), VELOCITY_STRUCT.pack(*velocity)
        room.store(obj.stream, ROOM_USER, now, pose_raw, vel_raw)
        if landed:
            obj.flight = None
        if room.recorded and not room.recording_paused:
            room.flight_seq += 1
            update = PoseUpdate.from_arrays(
                room.flight_seq,
                [obj.stream],
                [now],
                np.array([pose], dtype=np.float64),
                velocities=np.array([velocity], dtype=np.float64),
            )
            room.record_pose(ROOM_USER, now, update, None)
