"""The 3D scene both viewers draw: floor, room volume, and one avatar per user.

A viser scene (three.js in the browser, driven from here). World frame as in
DESIGN.md: +y up, metres. Every avatar is a set of stream nodes, one per
stream and per *layer*: the first layer (the ground truth in a replay, the
first interpolator live) is solid in the user's colour; every further layer is
a translucent ghost in its method's colour, so the same user drawn by several
interpolators can be told apart. A stream node is a frame posed with
``[px, py, pz, qw, qx, qy, qz]`` (viser takes ``wxyz`` too: no conversion),
with its geometry as children: a head box with a nose along -z (the view
direction), a controller box, or a sphere for a held object (``object:*``).
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

__all__ = ["GHOST_OPACITY", "METHOD_COLOURS", "AvatarScene", "user_colour"]

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

_HEAD = (0.18, 0.22, 0.2)
_NOSE = (0.04, 0.04, 0.14)
_HAND = (0.05, 0.05, 0.14)
_OBJECT_RADIUS = 0.06


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
        spread: float = 0.0,
    ) -> None:
        self.server = server
        self.layers = tuple(layers)
        #: Draw the n-th user seen ``n * spread`` m along +x (0: where they are). Users
        #: recorded in rooms of their own all stand near the origin; this sets them apart.
        self.spread = spread
        self._slots: dict[int, int] = {}
        self.avatars: dict[int, _Avatar] = {}
        self.hidden_layers: set[str] = set()
        #: What was last shown: (user, stream name) -> {layer: pose (7,)}.
        self.shown: dict[tuple[int, str], dict[str, NDArray[np.float64]]] = {}
        scene = server.scene
        cam = server.initial_camera
        cam.up = (0.0, 1.0, 0.0)
        cam.position = (0.6, 2.4, 3.2)
        cam.look_at = (0.0, 1.2, 0.0)
        scene.set_up_direction("+y")
        scene.world_axes.visible = False
        scene.add_grid("/floor", width=8.0, height=8.0, plane="xz", cell_size=0.5)
        lo, hi = np.asarray(volume.lo), np.asarray(volume.hi)
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
        if stream == "head":
            scene.add_box(f"{path}/box", color=colour, dimensions=_HEAD, opacity=opacity)
            # The nose points along -z: the view direction of an OpenXR head.
            scene.add_box(
                f"{path}/nose",
                color=colour,
                dimensions=_NOSE,
                position=(0.0, -0.02, -0.15),
                opacity=opacity,
            )
        elif stream.startswith("object:"):
            scene.add_icosphere(
                f"{path}/ball", radius=_OBJECT_RADIUS, color=colour, opacity=opacity
            )
        else:
            scene.add_box(f"{path}/box", color=colour, dimensions=_HAND, opacity=opacity)
        node.visible = layer not in self.hidden_layers
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
        dx = self.offset(user)
        for layer, pose in poses.items():
            node = self._node(av, layer, stream)
            node.position = (float(pose[0]) + dx, float(pose[1]), float(pose[2]))
            node.wxyz = (float(pose[3]), float(pose[4]), float(pose[5]), float(pose[6]))
        self.shown[(user, stream)] = poses
        if stream == "head" and self.layers[0] in poses:
            p = poses[self.layers[0]]
            av.label.position = (float(p[0]) + dx, float(p[1]) + 0.25, float(p[2]))

    def aim(self, users: int) -> None:
        """Point the initial camera at the middle of ``users`` users drawn ``spread`` apart."""
        mid = (users - 1) * self.spread / 2
        cam = self.server.initial_camera
        cam.look_at = (mid, 1.2, 0.0)
        cam.position = (mid + 0.6, 2.4, 3.2 + 0.8 * mid)

    def offset(self, user: int) -> float:
        """How far along +x ``user`` is drawn from where it is (see ``spread``)."""
        if not self.spread:
            return 0.0
        slot = self._slots.setdefault(user, len(self._slots))
        return slot * self.spread

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
        self.shown.pop((user, stream), None)

    def unhide_stream(self, user: int, stream: str) -> None:
        av = self.avatars.get(user)
        if av is None:
            return
        for (layer, s), node in av.nodes.items():
            if s == stream:
                node.visible = layer not in self.hidden_layers

    def set_user_visible(self, user: int, visible: bool) -> None:
        av = self.avatars.get(user)
        if av is not None:
            av.label.visible = visible
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
