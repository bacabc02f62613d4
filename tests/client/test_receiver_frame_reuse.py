"""What a render frame keeps from one frame to the next, and what it must not.

:func:`client.render.render_buffers` keeps, per thread, the rows it gathers
the bracketing keyframes into, the views of a room's arrays (until rows are
added), and each method set's plan (until the interpolator registry changes),
so that a frame of 100 streams costs a few dozen numpy calls. None of that may
leak into what a frame returns: each frame's poses are its own, a plug-in gets
its own copies, streams added after a render are rendered, and a method
registered again renders as its new self at once.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
from numpy.typing import ArrayLike, NDArray
from test_receiver_room import former_render, trace_room

from posecast import interp
from posecast.client.buffers import RoomBuffers
from posecast.client.render import render_buffers
from posecast.interp import registry

F64 = NDArray[np.float64]
PAIRS = ["soa", "dq-slerp", "motor-lerp"]


@pytest.fixture
def isolated_registry(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """Plug-ins registered in a test leave the registry as it was."""
    monkeypatch.setattr(registry, "_REGISTRY", dict(registry._REGISTRY))
    yield


def hand_back_a(a: ArrayLike, b: ArrayLike, s: ArrayLike) -> F64:
    """A careless plug-in: it returns the array it was given, not a copy."""
    return np.asarray(a)


def hand_back_b(a: ArrayLike, b: ArrayLike, s: ArrayLike) -> F64:
    return np.asarray(b)


def test_each_frame_owns_its_poses(isolated_registry: None) -> None:
    """A frame's poses do not change when the next frames render (kernels and plug-ins)."""
    interp.register("x-hold", hand_back_a)
    room, bufs, t0, t1 = trace_room(40)
    methods = [*PAIRS, "x-hold"]
    times = np.linspace(t0 + 0.1, t1 - 0.1, 7)
    frames = [render_buffers(room, float(t), methods) for t in times]
    kept = [{m: f.poses[m].copy() for m in methods} for f in frames]
    for _ in range(3):  # more frames, at other times
        render_buffers(room, float(times[3]) + 0.01, methods)
    for t, f, k in zip(times, frames, kept, strict=True):
        want, _ = former_render(bufs, float(t), PAIRS)
        for m in methods:
            np.testing.assert_array_equal(f.poses[m], k[m], err_msg=f"{m} at {t}")
        for m in PAIRS:
            np.testing.assert_array_equal(f.poses[m], want[m], err_msg=f"{m} at {t}")
    # The plug-in saw the bracket's first keyframes (held ones where stalled).
    lo_poses = former_render(bufs, float(times[0]), ["soa"])[0]["soa"]
    moving = ~frames[0].stalled
    assert np.any(moving)
    np.testing.assert_array_equal(frames[0].poses["x-hold"][~moving], lo_poses[~moving])


def test_a_method_registered_again_renders_as_its_new_self(isolated_registry: None) -> None:
    """Replacing a plug-in (``replace=True``) changes the very next frame."""
    room, _, t0, t1 = trace_room(10)
    t = 0.5 * (t0 + t1)
    interp.register("x-end", hand_back_a)
    first = render_buffers(room, t, ["soa", "x-end"]).poses["x-end"].copy()
    interp.register("x-end", hand_back_b, replace=True)
    second = render_buffers(room, t, ["soa", "x-end"])
    assert not np.array_equal(first, second.poses["x-end"])
    interp.register("x-end", hand_back_a, replace=True)
    np.testing.assert_array_equal(render_buffers(room, t, ["soa", "x-end"]).poses["x-end"], first)


def test_streams_added_after_a_render_are_rendered() -> None:
    """New rows are in the next frame, in order: within the room's arrays, and when it
    grows them (16 rows, then 32)."""
    room, bufs, t0, t1 = trace_room(10)
    t = 0.5 * (t0 + t1)
    before = render_buffers(room, t, PAIRS)
    assert before.poses["soa"].shape == (10, 7)
    _, more, _, _ = trace_room(10, seed=3)
    for count, grown in ((4, False), (6, True)):  # 14 rows fit in 16; 20 do not
        for src in more[:count]:
            buf = room.stream(capacity=12, has_velocities=src.has_velocities)
            for tk, p, v in zip(src.times, src.poses, src.velocities, strict=True):
                buf.push(tk, p, velocity=v)
            bufs.append(buf)
        del more[:count]
        assert (room.counts.shape[0] > 16) == grown
        after = render_buffers(room, t, PAIRS)
        want, stalled = former_render(bufs, t, PAIRS)
        np.testing.assert_array_equal(after.stalled, stalled)
        for m in PAIRS:
            assert after.poses[m].shape == (len(bufs), 7)
            np.testing.assert_array_equal(after.poses[m], want[m])
            np.testing.assert_array_equal(after.poses[m][:10], before.poses[m])


def test_rooms_of_other_sizes_in_turn_render_their_own_streams() -> None:
    """Two rooms of different sizes rendered alternately (one thread's rows change width)."""
    big, big_bufs, b0, b1 = trace_room(30)
    small, small_bufs, s0, s1 = trace_room(5, seed=1)
    for k in range(4):
        room, bufs, lo, hi = (big, big_bufs, b0, b1) if k % 2 else (small, small_bufs, s0, s1)
        t = lo + (hi - lo) * (0.3 + 0.1 * k)
        frame = render_buffers(room, t, PAIRS)
        want, _ = former_render(bufs, t, PAIRS)
        for m in PAIRS:
            np.testing.assert_array_equal(frame.poses[m], want[m])


def test_an_empty_room_after_a_full_one_renders_nothing() -> None:
    """The kept views do not outlive the room they were made for."""
    room, _, t0, t1 = trace_room(8)
    render_buffers(room, 0.5 * (t0 + t1), PAIRS)
    empty = RoomBuffers()
    empty.stream()
    frame = render_buffers(empty, 1.0, PAIRS)
    assert all(p.shape == (0, 7) for p in frame.poses.values())
