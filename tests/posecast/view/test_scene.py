"""The avatar scene on a real viser server (no browser): nodes, layers, users."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
import viser

from posecast.view.scene import AvatarScene, user_colour

POSE = np.array([0.1, 1.6, -0.2, 1.0, 0.0, 0.0, 0.0])


@pytest.fixture
def server() -> Iterator[viser.ViserServer]:
    srv = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    yield srv
    srv.stop()


def test_streams_are_posed_per_layer(server: viser.ViserServer) -> None:
    """Every stream (head, hand, held object) gets a node per layer, posed as given."""
    scene = AvatarScene(server, ("truth", "soa"), spread=2.0)
    ghost = POSE + np.array([0.05, 0, 0, 0, 0, 0, 0])
    for stream in ("head", "left", "object:drill"):
        scene.show(7, "u7", stream, {"truth": POSE, "soa": ghost})
    scene.show(9, "u9", "head", {"truth": POSE})
    av = scene.avatars[7]
    assert set(av.nodes) == {
        (lay, s) for lay in ("truth", "soa") for s in ("head", "left", "object:drill")
    }
    assert np.allclose(av.nodes[("soa", "left")].position, ghost[:3])
    assert np.allclose(av.nodes[("truth", "head")].wxyz, POSE[3:])
    # The second user seen is drawn one spread further along x.
    assert np.allclose(
        scene.avatars[9].nodes[("truth", "head")].position, POSE[:3] + np.array([2.0, 0, 0])
    )
    assert user_colour(7) != user_colour(9)


def test_layers_hide_and_users_go(server: viser.ViserServer) -> None:
    """Hiding a layer hides its nodes on every avatar, also ones drawn later; a user
    who leaves is gone from the scene."""
    scene = AvatarScene(server, ("soa", "dq-slerp"))
    scene.show(1, "u1", "head", {"soa": POSE, "dq-slerp": POSE})
    scene.set_layer_visible("dq-slerp", False)
    scene.show(2, "u2", "head", {"soa": POSE, "dq-slerp": POSE})
    for user in (1, 2):
        nodes = scene.avatars[user].nodes
        assert nodes[("soa", "head")].visible and not nodes[("dq-slerp", "head")].visible
    scene.remove_user(1)
    assert 1 not in scene.avatars and (1, "head") not in scene.shown
