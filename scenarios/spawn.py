"""Spawn points: where each user of a room stands, so that rooms have real distances.

Every bundled trace was recorded by one person in a room of their own, so every
user plays near the origin: a room of bots is a crowd standing in one spot. A
*layout* gives user ``i`` of ``n`` a spawn point (a place on the floor and a
direction to face); a user's motion is then moved there by one rigid map, a
:class:`Placement` (a turn about the vertical axis through the origin, then a
shift along the floor), applied to every pose of every stream of that user.

Layouts (``--spawn`` of ``bots``, ``demo`` and ``replay``):

- ``circle`` (``circle:R``): users evenly on a circle of radius R metres around the
  origin, facing its centre; without R, neighbours stand :data:`CIRCLE_SPACING` m
  apart along the circle (R = n * spacing / 2 pi, at least :data:`MIN_RADIUS` m);
- ``grid`` (``grid:S``): rows of ceil(sqrt(n)) users S m apart (default
  :data:`GRID_SPACING`), centred on the origin, all facing -z (forward in OpenXR);
- ``none``: everyone where their motion is (what the bots did before);
- a JSON file: ``{"spawns": [{"x": 1.0, "z": -2.0, "face_deg": 180}, ...]}``, one
  entry per user (``face_deg``: the direction faced, degrees about +y from -z;
  default 0); more users than entries is an error.

The placement that puts a motion on a spawn point is worked out from the motion
itself (:func:`placement_for`): its head's first horizontal position goes to the
point, and the head's mean horizontal heading over the first seconds turns to
face the point's direction. A placement is a rigid map of the world frame, so it
changes no error of DESIGN.md's QoE (positions, rotations, tips and velocities
move together; ``tests/scenarios/test_spawn.py`` checks it on a real trace), and
it is carried in the motion's label (``scenarios.motion.MotionSpec``) so that a
receiver rebuilds the placed ground truth exactly.

Pure code: no I/O but reading a layout file, no clock.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from posecast.interp import quat_mul
from posecast.scenarios.traces import Trace, TraceError

__all__ = [
    "CIRCLE_SPACING",
    "GRID_SPACING",
    "LAYOUTS",
    "MIN_RADIUS",
    "Placement",
    "SpawnPoint",
    "check_inside",
    "layout_points",
    "place",
    "placement_for",
]

#: Metres between neighbours along a ``circle`` whose radius is not given.
CIRCLE_SPACING = 1.5
#: The smallest radius of a ``circle`` whose radius is not given (m).
MIN_RADIUS = 1.5
#: Metres between neighbours of a ``grid`` whose spacing is not given.
GRID_SPACING = 2.0
#: The layouts by name (a JSON file is the other choice).
LAYOUTS = ("circle", "grid", "none")
#: Seconds of head motion whose mean heading is taken as the direction a motion faces.
_HEADING_WINDOW = 3.0

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class SpawnPoint:
    """A place on the floor (x, z in metres) and the direction faced there
    (``face_deg``: degrees about +y, 0 facing -z, 90 facing -x)."""

    x: float
    z: float
    face_deg: float = 0.0


@dataclass(frozen=True)
class Placement:
    """A rigid map of the world: turn by ``yaw_deg`` about +y through the origin, then
    shift by (``x``, 0, ``z``) metres. Values are rounded on construction (0.1 mm,
    0.001 deg) so that the label's text gives back the very same map."""

    yaw_deg: float
    x: float
    z: float

    def __post_init__(self) -> None:
        for name, digits in (("yaw_deg", 3), ("x", 4), ("z", 4)):
            value = float(getattr(self, name))
            if not math.isfinite(value):
                raise TraceError(f"placement {name} must be finite, got {value}")
            object.__setattr__(self, name, round(value, digits) + 0.0)  # no -0.0

    def label(self) -> str:
        """``yaw,x,z`` as :meth:`parse` reads it back."""
        return f"{self.yaw_deg!r},{self.x!r},{self.z!r}"

    @classmethod
    def parse(cls, text: str) -> Placement:
        try:
            yaw, x, z = (float(v) for v in text.split(","))
        except ValueError:
            raise TraceError(f"malformed placement {text!r} (want yaw_deg,x,z)") from None
        return cls(yaw, x, z)

    def then(self, other: Placement) -> Placement:
        """This map followed by ``other`` (rigid maps about +y compose into one)."""
        c, s = _cos_sin(other.yaw_deg)
        x = c * self.x + s * self.z + other.x
        z = -s * self.x + c * self.z + other.z
        return Placement(self.yaw_deg + other.yaw_deg, x, z)

    def apply(self, poses: NDArray[Any]) -> F64:
        """Poses ``(..., 7)`` moved by the map (a new array)."""
        poses = np.asarray(poses, dtype=np.float64)
        c, s = _cos_sin(self.yaw_deg)
        out = poses.copy()
        px, pz = poses[..., 0], poses[..., 2]
        out[..., 0] = c * px + s * pz + self.x
        out[..., 2] = -s * px + c * pz + self.z
        half = math.radians(self.yaw_deg) / 2
        turn = np.array([math.cos(half), 0.0, math.sin(half), 0.0])
        out[..., 3:] = quat_mul(np.broadcast_to(turn, poses[..., 3:].shape), poses[..., 3:])
        return out


def _cos_sin(deg: float) -> tuple[float, float]:
    r = math.radians(deg)
    return math.cos(r), math.sin(r)


def _heading_deg(q: F64) -> float:
    """The mean horizontal direction of -z under rotations ``q`` (N, 4), as ``face_deg``."""
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    # -z rotated by q: minus the third column of its rotation matrix.
    fx = -2.0 * (x * z + w * y)
    fz = -(1.0 - 2.0 * (x * x + y * y))
    mx, mz = float(np.mean(fx)), float(np.mean(fz))
    if math.hypot(mx, mz) < 1e-9:  # looks straight up or down on average: call it -z
        return 0.0
    # face_deg f turns -z to (-sin f, -cos f).
    return math.degrees(math.atan2(-mx, -mz))


def placement_for(trace: Trace, point: SpawnPoint) -> Placement:
    """The rigid map that puts ``trace``'s user on ``point``: the head's first
    horizontal position onto the point, its mean heading over the first seconds
    onto ``point.face_deg``. A trace without a ``head`` stream uses its first one."""
    j = trace.streams.index("head") if "head" in trace.streams else 0
    head = trace.poses[:, j, :]
    first = trace.times <= trace.times[0] + _HEADING_WINDOW
    yaw = point.face_deg - _heading_deg(head[first, 3:])
    yaw = (yaw + 180.0) % 360.0 - 180.0
    turned = Placement(yaw, 0.0, 0.0).apply(head[0])
    return Placement(yaw, point.x - float(turned[0]), point.z - float(turned[2]))


def place(trace: Trace, placement: Placement | None) -> Trace:
    """``trace`` with every pose of every stream moved by ``placement`` (None: as is)."""
    if placement is None:
        return trace
    return Trace(trace.name, trace.times, placement.apply(trace.poses), trace.streams)


def check_inside(trace: Trace, lo: tuple[float, ...], hi: tuple[float, ...], who: str) -> None:
    """Refuse, in one line, a placed motion that leaves the room's volume [lo, hi]."""
    p = trace.poses[..., :3].reshape(-1, 3)
    low, high = p.min(axis=0), p.max(axis=0)
    if np.all(low >= np.asarray(lo)) and np.all(high <= np.asarray(hi)):
        return
    box = ", ".join(f"{a}: {lo[k]:g}..{hi[k]:g}" for k, a in enumerate("xyz"))
    got = ", ".join(f"{a}: {low[k]:.2f}..{high[k]:.2f}" for k, a in enumerate("xyz"))
    raise TraceError(
        f"{who} leaves the room's volume ({box} m) at its spawn point ({got} m): "
        "use a smaller layout (--spawn circle:R, grid:S) or fewer users"
    )


def layout_points(layout: str, n: int) -> list[SpawnPoint] | None:
    """The spawn points of ``n`` users for ``layout`` (see the module docstring);
    None for ``none``. Bad input raises :class:`TraceError` with a one-line reason."""
    if n < 1:
        raise TraceError(f"a layout needs at least one user, got {n}")
    kind, _, arg = layout.partition(":")
    if kind == "none" and not arg:
        return None
    if kind in ("circle", "grid"):
        size = _size(layout, arg)
        return _circle(n, size) if kind == "circle" else _grid(n, size)
    path = Path(layout)
    if path.suffix.lower() == ".json" or path.exists():
        return _from_file(path, n)
    raise TraceError(
        f"unknown spawn layout {layout!r}: give circle, circle:R, grid, grid:S, none "
        "or a JSON file of spawn points"
    )


def _size(layout: str, arg: str) -> float | None:
    if not arg:
        return None
    try:
        size = float(arg)
    except ValueError:
        size = float("nan")
    if not (math.isfinite(size) and size > 0):
        raise TraceError(f"spawn layout {layout!r}: the size must be a positive number of metres")
    return size


def _circle(n: int, radius: float | None) -> list[SpawnPoint]:
    if radius is None:
        radius = max(MIN_RADIUS, n * CIRCLE_SPACING / (2 * math.pi))
    out = []
    for i in range(n):
        a = 2 * math.pi * i / n
        # Start in front of the origin (at -z, as a user looking forward sees it)
        # and go round; everyone faces the centre.
        x, z = radius * math.sin(a), -radius * math.cos(a)
        face = math.degrees(math.atan2(x, z))  # towards (0, 0): (-x, -z) = (-sin f, -cos f)
        out.append(SpawnPoint(round(x, 4), round(z, 4), round(face, 3)))
    return out


def _grid(n: int, spacing: float | None) -> list[SpawnPoint]:
    s = GRID_SPACING if spacing is None else spacing
    cols = math.ceil(math.sqrt(n))
    rows = math.ceil(n / cols)
    return [
        SpawnPoint(
            round((i % cols - (cols - 1) / 2) * s, 4), round((i // cols - (rows - 1) / 2) * s, 4)
        )
        for i in range(n)
    ]


def _from_file(path: Path, n: int) -> list[SpawnPoint]:
    try:
        doc = json.loads(path.read_text())
    except OSError as exc:
        raise TraceError(f"cannot read spawn layout {path}: {exc.strerror or exc}") from None
    except json.JSONDecodeError as exc:
        raise TraceError(
            f"spawn layout {path} is not JSON: {exc.msg} (line {exc.lineno})"
        ) from None
    spawns = doc.get("spawns") if isinstance(doc, dict) else None
    if not isinstance(spawns, list) or not spawns:
        raise TraceError(f'spawn layout {path}: want {{"spawns": [{{"x": .., "z": ..}}, ...]}}')
    points = []
    for k, entry in enumerate(spawns):
        try:
            points.append(
                SpawnPoint(float(entry["x"]), float(entry["z"]), float(entry.get("face_deg", 0.0)))
            )
        except (TypeError, KeyError, ValueError, AttributeError):
            raise TraceError(
                f"spawn layout {path}: entry {k} needs numbers x and z (and optional face_deg)"
            ) from None
        if not all(math.isfinite(v) for v in (points[-1].x, points[-1].z, points[-1].face_deg)):
            raise TraceError(f"spawn layout {path}: entry {k} is not finite")
    if len(points) < n:
        raise TraceError(f"spawn layout {path} has {len(points)} spawn points for {n} users")
    return points[:n]
