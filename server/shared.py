"""A shared object's state: who holds it, its clock offset and its flight.

The data of ``server/objects.py``'s rules, apart so that a room
(``server/room.py``) can hold its objects without depending on those rules:
:class:`RoomObject` is one object as the relay keeps it, :class:`Flight` the
motion of a thrown one (see ``server/objects.py`` for both rules).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

__all__ = [
    "GRAVITY",
    "MIN_STEP",
    "POSE_STRUCT",
    "RESTED",
    "VELOCITY_STRUCT",
    "Flight",
    "RoomObject",
    "Vec3",
    "pose_bytes",
]

GRAVITY = 9.81
#: An object's first keyframe after a change of owner comes at least this much
#: after its last one (s).
MIN_STEP = 1e-3
#: A thrown object's last keyframe older than this (s) at the release: it lay still
#: until the release, and flies from then.
RESTED = 0.1
POSE_STRUCT = struct.Struct("<7f")
VELOCITY_STRUCT = struct.Struct("<6e")

Vec3 = tuple[float, float, float]


def _quat_mul(a: tuple[float, ...], b: tuple[float, ...]) -> tuple[float, float, float, float]:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


@dataclass(frozen=True)
class Flight:
    """A thrown object's motion from its release keyframe until it rests on the floor."""

    t0: float
    pose: tuple[float, ...]
    """[px, py, pz, qw, qx, qy, qz] at ``t0``."""
    velocity: Vec3
    angular: Vec3
    floor: float

    def landing(self) -> float:
        """Time after ``t0`` at which it reaches the floor (0 if it starts on or below it)."""
        y, vy = max(self.pose[1] - self.floor, 0.0), self.velocity[1]
        return (vy + math.sqrt(vy * vy + 2.0 * GRAVITY * y)) / GRAVITY

    def at(self, t: float) -> tuple[tuple[float, ...], tuple[float, ...], bool]:
        """(pose, velocity [vx, vy, vz, wx, wy, wz], landed) at time ``t``."""
        land = self.landing()
        dt = min(max(t - self.t0, 0.0), land)
        px, py, pz = self.pose[:3]
        vx, vy, vz = self.velocity
        position = (px + vx * dt, py + vy * dt - 0.5 * GRAVITY * dt * dt, pz + vz * dt)
        wx, wy, wz = self.angular
        rate = math.sqrt(wx * wx + wy * wy + wz * wz)
        q = self.pose[3:]
        if rate > 0.0:
            half = 0.5 * rate * dt
            s = math.sin(half) / rate
            q = _quat_mul((math.cos(half), wx * s, wy * s, wz * s), q)
        landed = t - self.t0 >= land
        if landed:
            return (position[0], max(position[1], self.floor), position[2], *q), (0.0,) * 6, True
        return (*position, *q), (vx, vy - GRAVITY * dt, vz, wx, wy, wz), False


@dataclass
class RoomObject:
    """One shared object of a room, as the relay keeps it."""

    name: str
    stream: int
    creator: int
    keep: bool = True
    steal: bool = False
    owner: int | None = None
    locked: bool = False
    flight: Flight | None = None
    #: Added to the current owner's capture times (see "Clocks at a handover").
    offset: float = 0.0
    #: The owner changed and its first keyframe has not come yet.
    fresh: bool = False

    def rebase(self, capture: float, last: float | None) -> float:
        """The stored time of the owner's keyframe captured at ``capture``."""
        if self.fresh:
            self.fresh = False
            self.offset = 0.0 if last is None else max(0.0, last + MIN_STEP - capture)
        return capture + self.offset

    def give(self, owner: int | None) -> None:
        self.owner, self.flight, self.fresh, self.offset = owner, None, True, 0.0
        if owner is None:
            self.locked = False


def pose_bytes(pose: tuple[float, ...]) -> bytes:
    return POSE_STRUCT.pack(*pose)
