"""The 3D scene both viewers draw: floor, room volume, and one avatar per user.

A viser scene (three.js in the browser, driven from here). World frame as in
DESIGN.md: +y up, metres. Every avatar is a set of stream nodes, one per
stream and per *layer*: the first layer (the ground truth in a replay, the
first interpolator live) is solid in the user's colour; every further layer is
a translucent ghost in its method's colour, so the same user drawn by several
interpolators can be told apart. A stream node is a frame posed with
``[px, py, pz, qw, qx, qy, qz]`` (viser takes ``wxyz`` too: no conversion),
with its geometry as children: a head (a sphere with a dark visor on its -z
side, where an OpenXR head looks), a controller (a grip and a tracking ring), or
a sphere for a held object (``object:*``). The first layer's head also stands on
a translucent body down to the floor, so users read as people standing in a room.

Where users are drawn: where they are (bots and replays stand users on spawn
points, ``scenarios.spawn``), except that a user whose head first shows up
within :data:`CROWDED` m of another user's is drawn shifted along +x (by
:data:`AUTO_STEP` m steps) until it stands clear, so recordings made before
spawn points (every user near the origin) stay readable. ``spread`` > 0 draws the
n-th user seen n * spread m along +x instead; ``spread`` 0 draws everyone where
they are, crowded or not. :meth:`AvatarScene.frame` points the camera at the room.
"""

from __future__ import annotations

import colorsys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import viser
from numpy.typing import NDArray

from posecast.protocol.codec import DEFAULT_VOLUME, Volume

__all__ = [
    "AUTO_STEP",
    "CROWDED",
    "GHOST_OPACITY",
    "METHOD_COLOURS",
    "AvatarScene",
    "method_colour",
    "user_colour",
]

#: Ghost colours by interpolator (others get a colour from their name's hash).
METHOD_COLOURS: dict[str, tuple[int, int, int]] = {
    "soa": (230, 120, 20),
    "dq-slerp": (30, 150, 230),
    "motor-lerp": (150, 60, 200),
    "motor-hermite": (20, 170, 90),
    "motor-cubic": (200, 50, 120),
    "motor-quintic": (120, 120, 20),
    "soa-hermite": (200, 180, 40),
}
GHOST_OPACITY = 0.5
#: Ghosts are drawn this much smaller than the solid layer.
GHOST_SCALE = 0.85

#: Geometry (m): the head sphere, the visor (width, height, depth) in front of it, the
#: controller grip (w, h, d) and ring (radius, thickness), the body under the head.
_HEAD_RADIUS = 0.11
_VISOR = (0.19, 0.075, 0.06)
_GRIP = (0.035, 0.035, 0.12)
_RING = (0.05, 0.014)
_BODY_RADIUS = 0.09
_VISOR_COLOUR = (30, 30, 40)
_OBJECT_RADIUS = 0.06
#: A user whose head first shows up this close (m, on the floor) to another's is moved.
CROWDED = 0.6
#: How far along +x a crowded user is moved at a time (m).
AUTO_STEP = 1.5
#: The initial camera's elevation above the room (degrees) and vertical field of view.
_ELEVATION_DEG = 32.0
_FOV_DEG = 50.0


def user_colour(user: int) -> tuple[int, int, int]:
    """A saturated colour per user id, spread around the hue circle (golden ratio)."""
    r, g, b = colorsys.hsv_to_rgb((user * 0.618034) % 1.0, 0.75, 0.9)
    return int(r * 255), int(g * 255), int(b * 255)


def method_colour(method: str) -> tuple[int, int, int]:
    if method in METHOD_COLOURS:
        return METHOD_COLOURS[method]
    r, g, b = colorsys.hsv_to_rgb((sum(map(ord, method)) * 0.137) % 1.0, 0.8, 0.8)
    return int(r * 255), int(g * 255), int(b * 255)


@dataclass
class _Avatar:
    user: int
    name: str
    colour: tuple[int, int, int]
    label: Any
    #: (layer, stream name) -> frame handle
    nodes: dict[tuple[str, str], Any] = field(default_factory=dict)
    body: Any = None
    #: A ball above the label in the colour of the user's current rate (None: no rate yet).
    rate: Any = None


def _forward(wxyz: NDArray[np.float64]) -> NDArray[np.float64]:
    """-z (where an OpenXR device points) rotated by a unit quaternion (w first)."""
    w, x, y, z = (float(v) for v in wxyz)
    return np.array(
        [-2.0 * (x * z + w * y), -2.0 * (y * z - w * x), -(1.0 - 2.0 * (x * x + y * y))]
    )


class AvatarScene:
    """Avatars of users in a viser scene; ``layers`` are what each stream is drawn as.

    ``layers[0]`` is drawn solid in the user's colour, the others as ghosts in
    their method's colour (:data:`METHOD_COLOURS`).
    """

    def __init__(
        self,
        server: viser.ViserServer,
        layers: Sequence[str],
        volume: Volume = DEFAULT_VOLUME,
        spread: float | None = None,
    ) -> None:
        self.server = server
        self.layers = tuple(layers)
        #: None: draw users where they are unless crowded (see the module docstring);
        #: > 0: the n-th user seen n * spread m along +x; 0: where they are.
        self.spread = spread
        self._offsets: dict[int, float] = {}
        #: Where each user's head was first drawn (x, z), for the crowd rule.
        self._first: dict[int, tuple[float, float]] = {}
        self.avatars: dict[int, _Avatar] = {}
        self.hidden_layers: set[str] = set()
        #: The user whose eyes the camera follows (None: the room camera).
        self.first_person: int | None = None
        #: What was last shown: (user, stream name) -> {layer: pose (7,)}.
        self.shown: dict[tuple[int, str], dict[str, NDArray[np.float64]]] = {}
        scene = server.scene
        cam = server.initial_camera
        cam.up = (0.0, 1.0, 0.0)
        cam.fov = np.radians(_FOV_DEG)
        self.frame(np.array([[-1.5, 1.6, -1.5], [1.5, 1.6, 1.5]]))
        scene.set_up_direction("+y")
        scene.world_axes.visible = False
        # No environment map: viser keeps the canvas nearly transparent until one is
        # loaded, which takes minutes in software WebGL on a busy machine. A sky light
        # and the default lights do instead.
        scene.configure_environment_map(None)
        scene.configure_default_lights(True, cast_shadow=False)
        scene.add_light_hemisphere(
            "/sky", sky_color=(255, 255, 255), ground_color=(120, 120, 130), intensity=1.6
        )
        lo, hi = np.asarray(volume.lo), np.asarray(volume.hi)
        size = float(min(hi[0] - lo[0], hi[2] - lo[2], 16.0))
        scene.add_grid("/floor", width=size, height=size, plane="xz", cell_size=0.5)
        scene.add_box(
            "/volume",
            color=(150, 150, 150),
            dimensions=tuple(hi - lo),
            wireframe=True,
            position=tuple((hi + lo) / 2),
        )

    def _ensure(self, user: int, name: str) -> _Avatar:
        av = self.avatars.get(user)
        if av is None:
            colour = user_colour(user)
            label = self.server.scene.add_label(
                f"/users/u{user}/label", name, position=(0.0, 2.0, 0.0), anchor="bottom-center"
            )
            av = self.avatars[user] = _Avatar(user, name, colour, label)
        elif av.name != name:
            av.label.text = name
            av.name = name
        return av

    def _node(self, av: _Avatar, layer: str, stream: str) -> Any:
        node = av.nodes.get((layer, stream))
        if node is not None:
            return node
        ghost = layer != self.layers[0]
        colour = method_colour(layer) if ghost else av.colour
        opacity = GHOST_OPACITY if ghost else None
        scene = self.server.scene
        path = f"/users/u{av.user}/{layer}/{stream.replace(':', '_')}"
        node = scene.add_frame(path, show_axes=False)
        # A ghost is a little smaller than the solid: where they agree the solid shows
        # in the user's colour; where a method strays, its ghost shows.
        size = GHOST_SCALE if ghost else 1.0
        if stream == "head":
            scene.add_icosphere(
                f"{path}/head",
                radius=_HEAD_RADIUS * size,
                color=colour,
                opacity=opacity,
                subdivisions=2,
            )
            # The visor faces -z: the view direction of an OpenXR head.
            scene.add_box(
                f"{path}/visor",
                color=_VISOR_COLOUR if not ghost else colour,
                dimensions=size * np.array(_VISOR),
                position=(0.0, 0.01, -0.085 * size),
                opacity=opacity,
            )
            if not ghost:
                av.body = scene.add_cylinder(
                    f"/users/u{av.user}/body",
                    radius=_BODY_RADIUS,
                    height=1.0,
                    color=colour,
                    opacity=0.25,
                    cast_shadow=False,
                    radial_segments=16,
                    wxyz=(np.sqrt(0.5), np.sqrt(0.5), 0.0, 0.0),  # its axis (z) upright
                )
        elif stream.startswith("object:"):
            scene.add_icosphere(
                f"{path}/ball", radius=_OBJECT_RADIUS, color=colour, opacity=opacity
            )
        else:
            # A controller: the grip along -z (where it points) and the ring above it.
            grip = size * np.array(_GRIP)
            scene.add_box(f"{path}/grip", color=colour, dimensions=grip, opacity=opacity)
            scene.add_cylinder(
                f"{path}/ring",
                radius=_RING[0] * size,
                height=_RING[1] * size,
                color=colour,
                opacity=opacity,
                radial_segments=16,
                position=(0.0, 0.03, -0.06),
                wxyz=(np.cos(0.35), np.sin(0.35), 0.0, 0.0),
            )
        node.visible = layer not in self.hidden_layers and not (
            stream == "head" and av.user == self.first_person
        )
        av.nodes[(layer, stream)] = node
        return node

    def show(
        self,
        user: int,
        name: str,
        stream: str,
        poses: dict[str, NDArray[np.float64]],
    ) -> None:
        """Pose one stream of ``user`` in each layer given (``poses[layer]``: (7,))."""
        av = self._ensure(user, name)
        if stream == "head" and user not in self._first and poses:
            self.anchor(user, next(iter(poses.values())))
        dx = self.offset(user)
        for layer, pose in poses.items():
            node = self._node(av, layer, stream)
            node.position = (float(pose[0]) + dx, float(pose[1]), float(pose[2]))
            node.wxyz = (float(pose[3]), float(pose[4]), float(pose[5]), float(pose[6]))
        self.shown[(user, stream)] = poses
        if stream == "head" and self.layers[0] in poses:
            p = poses[self.layers[0]]
            x, y, z = float(p[0]) + dx, float(p[1]), float(p[2])
            av.label.position = (x, y + 0.3, z)
            if av.rate is not None:
                av.rate.position = (x, y + 0.25, z)
            if av.body is not None:
                tall = max(0.2, y - 0.25)
                av.body.position = (x, tall / 2, z)
                av.body.scale = (1.0, 1.0, tall)
            if user == self.first_person:
                self._look_from(p, dx)

    def anchor(self, user: int, head: NDArray[np.float64]) -> None:
        """Fix where ``user`` is drawn from its first head pose (the crowd rule)."""
        x, z = float(head[0]), float(head[2])
        dx = 0.0
        if self.spread is None:
            taken = [(fx + self._offsets.get(u, 0.0), fz) for u, (fx, fz) in self._first.items()]
            while any(np.hypot(x + dx - tx, z - tz) < CROWDED for tx, tz in taken):
                dx += AUTO_STEP
            self._offsets[user] = dx
        self._first[user] = (x, z)

    def offset(self, user: int) -> float:
        """How far along +x ``user`` is drawn from where it is (see the module docstring)."""
        if self.spread is None:
            return self._offsets.get(user, 0.0)
        if not self.spread:
            return 0.0
        if user not in self._offsets:
            self._offsets[user] = len(self._offsets) * self.spread
        return self._offsets[user]

    # -- the camera ------------------------------------------------------------------

    def frame(self, points: NDArray[np.float64]) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """Point the camera (the initial one, and every open page's) at a room holding
        ``points`` (N, 3): from behind them (+z) and above, far enough to see all; the
        (position, look-at) it chose."""
        pts = np.atleast_2d(np.asarray(points, dtype=np.float64))
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        centre = (lo + hi) / 2
        half = max(1.2, float(np.hypot(hi[0] - lo[0], hi[2] - lo[2])) / 2 + 0.6)
        dist = 1.1 * half / np.tan(np.radians(_FOV_DEG) / 2)
        el = np.radians(_ELEVATION_DEG)
        look = (float(centre[0]), 1.0, float(centre[2]))
        pos = (look[0], 1.0 + dist * float(np.sin(el)), look[2] + dist * float(np.cos(el)))
        init = self.server.initial_camera
        init.up = (0.0, 1.0, 0.0)
        init.position, init.look_at = pos, look
        for client in self.server.get_clients().values():
            client.camera.up_direction = (0.0, 1.0, 0.0)
            client.camera.position, client.camera.look_at = pos, look
        return pos, look

    def frame_users(self) -> None:
        """:meth:`frame` the heads shown now (nothing shown: leave the camera)."""
        heads = [
            poses[self.layers[0]][:3] + np.array([self.offset(u), 0.0, 0.0])
            for (u, s), poses in self.shown.items()
            if s == "head" and self.layers[0] in poses
        ]
        if heads and self.first_person is None:
            self.frame(np.array(heads))

    def aim(self, users: int) -> None:
        """Point the camera at ``users`` users drawn ``spread`` apart (before any shows)."""
        step = self.spread or AUTO_STEP
        self.frame(np.array([[0.0, 1.6, -0.5], [(users - 1) * step, 1.6, 0.5]]))

    def set_first_person(self, user: int | None) -> None:
        """Look through ``user``'s eyes (their head hidden), or back at the room (None)."""
        old, self.first_person = self.first_person, user
        for u in (old, user):
            av = self.avatars.get(u) if u is not None else None
            if av is not None:
                for (layer, s), node in av.nodes.items():
                    if s == "head":
                        node.visible = u != user and layer not in self.hidden_layers
        if user is None:
            self.frame_users()
        elif (user, "head") in self.shown:
            poses = self.shown[(user, "head")]
            self._look_from(next(iter(poses.values())), self.offset(user))

    def _look_from(self, head: NDArray[np.float64], dx: float) -> None:
        eye = np.array([float(head[0]) + dx, float(head[1]), float(head[2])])
        fwd = _forward(head[3:7])
        for client in self.server.get_clients().values():
            cam = client.camera
            cam.up_direction = (0.0, 1.0, 0.0)
            cam.position, cam.look_at = eye, eye + fwd

    # -- layers, users, streams ------------------------------------------------------

    def set_layer_visible(self, layer: str, visible: bool) -> None:
        """Show or hide one layer (a ghost method) on every avatar."""
        (self.hidden_layers.discard if visible else self.hidden_layers.add)(layer)
        for av in self.avatars.values():
            for (lay, _), node in av.nodes.items():
                if lay == layer:
                    node.visible = visible

    def layer_toggle(self, layer: str) -> Callable[[Any], None]:
        """A checkbox callback that shows ``layer`` while the box is ticked."""

        def toggle(event: Any) -> None:
            self.set_layer_visible(layer, bool(event.target.value))

        return toggle

    def hide_stream(self, user: int, stream: str) -> None:
        """Hide a stream (e.g. a user or stream deselected in a replay)."""
        av = self.avatars.get(user)
        if av is None:
            return
        for (_, s), node in av.nodes.items():
            if s == stream:
                node.visible = False
        if stream == "head" and av.body is not None:
            av.body.visible = False
        self.shown.pop((user, stream), None)

    def unhide_stream(self, user: int, stream: str) -> None:
        av = self.avatars.get(user)
        if av is None:
            return
        for (layer, s), node in av.nodes.items():
            if s == stream:
                node.visible = layer not in self.hidden_layers
        if stream == "head" and av.body is not None:
            av.body.visible = True

    def set_rate_colour(self, user: int, colour: tuple[int, int, int]) -> None:
        """Colour ``user``'s rate ball (under its name label; made on first call)."""
        av = self.avatars.get(user)
        if av is None:
            return
        if av.rate is None:
            x, y, z = av.label.position
            av.rate = self.server.scene.add_icosphere(
                f"/users/u{user}/rate", radius=0.05, color=colour, position=(x, y - 0.05, z)
            )
        elif tuple(av.rate.color) != colour:
            av.rate.color = colour

    def set_user_visible(self, user: int, visible: bool) -> None:
        av = self.avatars.get(user)
        if av is not None:
            av.label.visible = visible
            if av.rate is not None:
                av.rate.visible = visible
            if av.body is not None:
                av.body.visible = visible
            for (layer, _), node in av.nodes.items():
                node.visible = visible and layer not in self.hidden_layers

    def remove_user(self, user: int) -> None:
        """Forget a user who left: its nodes go from the scene."""
        av = self.avatars.pop(user, None)
        if av is None:
            return
        self.server.scene.remove_by_name(f"/users/u{user}")
        for key in [k for k in self.shown if k[0] == user]:
            del self.shown[key]
        if self.first_person == user:
            self.set_first_person(None)
