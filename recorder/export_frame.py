"""Times and world frame of an export (:func:`recorder.export.export`'s ``times``, ``z_up``).

Recorded times are the server clock; an export may give them as they are
(``server``), as seconds since the recording started (``relative``) or as UNIX
wall-clock time (``wall``), from the start times in the recording's header. The
world may be turned z-up (+90 deg about x: +z up, +y forward, +x right), the
convention of ROS and Foxglove, with poses, velocities and throw velocities.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "TIME_BASES",
    "Y_UP_FRAME",
    "Z_UP_FRAME",
    "TimeBase",
    "as_exported",
    "export_description",
]

TimeBase = Literal["server", "relative", "wall"]
TIME_BASES = ("server", "relative", "wall")

#: The world frame's name in exports: as recorded (OpenXR, +y up), or turned z-up.
Y_UP_FRAME = "world"
Z_UP_FRAME = "world_z_up"
_FRAMES = {
    Y_UP_FRAME: "right-handed, +y up, +z backward (OpenXR), as recorded",
    Z_UP_FRAME: "right-handed, +z up, +y forward, +x right: the recording's world "
    "turned +90 deg about x",
}
#: The turn from y-up to z-up, a unit quaternion (w first): +90 deg about x.
_Z_UP_TURN = np.array([math.sqrt(0.5), math.sqrt(0.5), 0.0, 0.0])


def _rotate(q: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
    """Vectors ``v`` (..., 3) turned by the unit quaternion ``q`` (w first)."""
    w, u = q[0], q[1:]
    t = 2.0 * np.cross(u, v)
    return np.asarray(v + w * t + np.cross(u, t))


def _turn_poses(poses: NDArray[np.float32]) -> NDArray[np.float32]:
    """Poses (N, 7) re-expressed in the z-up world: p -> R p, q -> q_turn * q."""
    p = poses[:, :3].astype(np.float64)
    q = poses[:, 3:].astype(np.float64)
    a, b = _Z_UP_TURN, q
    turned_q = np.stack(
        [
            a[0] * b[:, 0] - a[1] * b[:, 1] - a[2] * b[:, 2] - a[3] * b[:, 3],
            a[0] * b[:, 1] + a[1] * b[:, 0] + a[2] * b[:, 3] - a[3] * b[:, 2],
            a[0] * b[:, 2] - a[1] * b[:, 3] + a[2] * b[:, 0] + a[3] * b[:, 1],
            a[0] * b[:, 3] + a[1] * b[:, 2] - a[2] * b[:, 1] + a[3] * b[:, 0],
        ],
        axis=1,
    )
    return np.concatenate([_rotate(_Z_UP_TURN, p), turned_q], axis=1).astype(np.float32)


def _turn_vec(v: Any) -> Any:
    """A 3-vector (or None) in the z-up world."""
    if v is None:
        return None
    return tuple(float(x) for x in _rotate(_Z_UP_TURN, np.asarray(v, dtype=np.float64)))


def _time_shift(session: dict[str, str], times: TimeBase) -> float:
    """What to add to a recorded server time for the time base ``times``."""
    if times == "server":
        return 0.0
    try:
        start = float(session["start_time"])
        wall = float(session["start_wall_time"]) if times == "wall" else 0.0
    except (KeyError, ValueError):
        raise ValueError(
            f"the recording's header has no start time, so no {times} times; use --time server"
        ) from None
    return wall - start


def as_exported(data: Any, times: TimeBase = "server", z_up: bool = False) -> Any:
    """``data`` (a ``recorder.export.SessionArrays``) with times in the base ``times``
    and, with ``z_up``, the world turned z-up."""
    shift = _time_shift(data.session, times)
    if shift == 0.0 and not z_up:
        return data
    streams = []
    for s in data.streams:
        vel = s.velocities
        if z_up and vel is not None:
            v = vel.astype(np.float64)
            vel = np.concatenate(
                [_rotate(_Z_UP_TURN, v[:, :3]), _rotate(_Z_UP_TURN, v[:, 3:])], axis=1
            ).astype(np.float32)
        streams.append(
            replace(
                s,
                times=s.times + shift,
                arrival=s.arrival + shift,
                poses=_turn_poses(s.poses) if z_up else s.poses,
                velocities=vel,
            )
        )
    tracks = [
        replace(
            t,
            created=t.created + shift,
            removed=None if t.removed is None else t.removed + shift,
            changes=tuple(
                replace(
                    c,
                    time=c.time + shift,
                    velocity=_turn_vec(c.velocity) if z_up else c.velocity,
                    angular=_turn_vec(c.angular) if z_up else c.angular,
                )
                for c in t.changes
            ),
        )
        for t in data.objects
    ]
    return replace(data, streams=streams, objects=tracks)


def export_description(times: TimeBase, z_up: bool, session: dict[str, str]) -> dict[str, str]:
    """What an export says about its times and frame (``streams.json``, NPZ, Foxglove)."""
    frame = Z_UP_FRAME if z_up else Y_UP_FRAME
    what = {
        "server": "s on the server clock, as recorded",
        "relative": "s since the recording started",
        "wall": "UNIX time, s",
    }[times]
    out = {"time": times, "time_unit": what, "frame": frame, "frame_axes": _FRAMES[frame]}
    if session.get("start_utc"):
        out["recording_start_utc"] = session["start_utc"]
    return out
