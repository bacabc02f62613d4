"""The avatar scene on a real viser server (no browser): nodes, layers, users."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
import viser

from posecast.view.scene import AUTO_STEP, CROWDED, AvatarScene, user_colour

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


def test_crowded_users_are_drawn_clear_of_each_other(server: viser.ViserServer) -> None:
    """By default users are drawn where they are; one whose head first shows up on
    another's is moved along +x in AUTO_STEP steps until it stands clear."""
    scene = AvatarScene(server, ("soa",))
    apart = POSE + np.array([3.0, 0, 0, 0, 0, 0, 0])
    for user, pose in ((1, POSE), (2, apart), (3, POSE), (4, POSE)):
        scene.show(user, f"u{user}", "head", {"soa": pose})
    assert [scene.offset(u) for u in (1, 2, 3, 4)] == [0.0, 0.0, AUTO_STEP, 3 * AUTO_STEP]
    drawn = np.array([scene.avatars[u].nodes[("soa", "head")].position for u in (1, 2, 3, 4)])
    gaps = np.linalg.norm(drawn[:, None, [0, 2]] - drawn[None, :, [0, 2]], axis=-1)
    assert gaps[np.triu_indices(4, 1)].min() >= CROWDED
    # spread 0: where they are, crowded or not.
    flat = AvatarScene(server, ("soa",), spread=0.0)
    for user in (1, 2):
        flat.show(user, f"u{user}", "head", {"soa": POSE})
    assert flat.offset(2) == 0.0


def test_frame_puts_the_room_in_view(server: viser.ViserServer) -> None:
    """The camera framed on a room sees every given point inside its field of view,
    from behind (+z) and above, looking at the room's middle."""
    scene = AvatarScene(server, ("soa",))
    pts = np.array([[-4.0, 1.6, -3.0], [4.0, 1.6, 3.0], [0.0, 0.2, 0.0]])
    pos, look = scene.frame(pts)
    p, c = np.array(pos), np.array(look)
    assert p[1] > 2.0 and p[2] > 3.0 and np.allclose(c[[0, 2]], 0.0)
    fwd = (c - p) / np.linalg.norm(c - p)
    fov = float(server.initial_camera.fov)
    for q in pts:
        d = (q - p) / np.linalg.norm(q - p)
        assert np.degrees(np.arccos(d @ fwd)) < np.degrees(fov / 2) * 1.3  # wide page


def test_first_person_hides_the_own_head(server: viser.ViserServer) -> None:
    """Looking through a user's eyes hides that user's head (not its hands, not others');
    back to the room shows it again; a user who leaves gives the room camera back."""
    scene = AvatarScene(server, ("soa", "dq-slerp"))
    for user in (1, 2):
        for stream in ("head", "left"):
            scene.show(user, f"u{user}", stream, {"soa": POSE, "dq-slerp": POSE})
    scene.set_first_person(1)
    nodes = scene.avatars[1].nodes
    assert not nodes[("soa", "head")].visible and not nodes[("dq-slerp", "head")].visible
    assert nodes[("soa", "left")].visible and scene.avatars[2].nodes[("soa", "head")].visible
    scene.set_first_person(None)
    assert nodes[("soa", "head")].visible
    scene.set_first_person(2)
    scene.remove_user(2)
    assert scene.first_person is None
