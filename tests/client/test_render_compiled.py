"""A render frame on the compiled kernels equals the numpy frame, on real motion.

:func:`client.render.render_buffers` brackets and interpolates with the compiled
render kernels where they are built (:mod:`interp.accel`) and with numpy
otherwise. Rooms of streams cut from the full ``dev`` recordings, keyframes
arriving late, out of order and twice, rendered both ways frame after frame:
every method (pair, window and velocity, and the velocity methods' fallback)
gives the same poses to float rounding and the same stalls, at one playout time
for all and at one per stream, for a whole room and for some of its buffers.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from posecast import interp
from posecast.client.buffers import RoomBuffers, StreamBuffer
from posecast.client.render import RenderFrame, render_buffers
from posecast.interp import accel
from posecast.scenarios.traces import find_traces, load_trace

ATOL = 1e-12
PAIRS = ("soa", "dq-slerp", "motor-lerp")


@pytest.fixture(scope="module")
def dev_room() -> tuple[RoomBuffers, list[StreamBuffer], float, float]:
    """27 streams (a bot's room of 10) of the dev recordings at 20 Hz, badly delivered."""
    if accel.compiled() is None:
        pytest.skip(f"the render kernels are not built here: {accel.IMPLEMENTATION}")
    rng = np.random.default_rng(28)
    traces = [load_trace(p) for p in find_traces("traces:dev")]
    velocities = [tr.causal_velocities() for tr in traces]  # once a trace, not a stream
    room = RoomBuffers(capacity=24)
    bufs = []
    for j in range(27):
        tr = traces[j % len(traces)]
        dev = (j // len(traces)) % len(tr.streams)
        vel = velocities[j % len(traces)][:, dev]
        buf = room.stream(has_velocities=j % 4 != 3)
        start = rng.uniform(0.0, tr.duration - 8.0)
        send = start + np.arange(0.0, 4.0, 1.0 / 20.0) + rng.uniform(-0.004, 0.004)
        idx = np.searchsorted(tr.times, send).clip(0, len(tr.times) - 1)
        order = np.concatenate([rng.permutation(g) for g in np.array_split(np.arange(80), 16)])
        for i in [*order, *rng.choice(order, 4)]:
            buf.push(
                float(tr.times[idx[i]] - start),
                tr.poses[idx[i], dev].astype(np.float32),
                velocity=vel[idx[i]],
            )
        bufs.append(buf)
    return room, bufs, 0.0, 4.0


def both(
    buffers: RoomBuffers | list[StreamBuffer], t: object, methods: list[str]
) -> Iterator[RenderFrame]:
    """The frame on numpy, then on the compiled kernels."""
    was_pure = accel.kernels is None
    try:
        for pure in (True, False):
            accel.use(pure)
            yield render_buffers(buffers, t, methods)  # type: ignore[arg-type]
    finally:
        accel.use(was_pure)


def assert_same(numpy_frame: RenderFrame, compiled: RenderFrame, where: str) -> None:
    np.testing.assert_array_equal(compiled.stalled, numpy_frame.stalled, err_msg=where)
    assert compiled.poses.keys() == numpy_frame.poses.keys()
    for m, want in numpy_frame.poses.items():
        got = compiled.poses[m]
        assert got.shape == want.shape
        np.testing.assert_allclose(got, want, rtol=0, atol=ATOL, err_msg=f"{m} {where}")


@pytest.mark.parametrize(
    "methods", [["soa"], list(PAIRS), interp.names()], ids=["soa", "pairs", "every"]
)
def test_frames_equal_on_dev_motion(
    dev_room: tuple[RoomBuffers, list[StreamBuffer], float, float], methods: list[str]
) -> None:
    """Frames at 45 Hz over the room's span and past it (stalls), exactly on keyframes."""
    room, bufs, t0, t1 = dev_room
    taus = [t0 - 0.2, *np.arange(t0, t1 + 0.3, 1.0 / 45.0), bufs[3].times[5], bufs[9].times[-1]]
    stalls = 0
    for t in taus:
        numpy_frame, compiled = both(room, float(t), methods)
        assert_same(numpy_frame, compiled, f"at {t}")
        stalls += int(compiled.stalled.sum())
    assert 0 < stalls < 27 * len(taus)


def test_per_stream_times_and_some_buffers(
    dev_room: tuple[RoomBuffers, list[StreamBuffer], float, float],
) -> None:
    """One playout time per stream (a late peer), and a list of some buffers."""
    room, bufs, t0, t1 = dev_room
    rng = np.random.default_rng(5)
    methods = [*PAIRS, "motor-hermite"]
    for _ in range(40):
        t = rng.uniform(t0 - 0.1, t1 + 0.1, len(room))
        assert_same(*both(room, t, methods), "per stream")
        picked = [bufs[i] for i in rng.choice(27, 9, replace=False)]
        tp = float(rng.uniform(t0, t1))
        assert_same(*both(picked, tp, methods), "picked")


def test_a_room_with_an_empty_row() -> None:
    """A stream with no keyframe yet is left out of the frame on both paths."""
    if accel.compiled() is None:
        pytest.skip(f"the render kernels are not built here: {accel.IMPLEMENTATION}")
    room = RoomBuffers(capacity=8)
    pose = np.array([0.0, 1.6, 0.0, 1.0, 0.0, 0.0, 0.0], np.float32)
    turned = np.array([0.5, 1.6, 0.0, 0.0, 0.0, 1.0, 0.0], np.float32)
    a, _, c = room.stream(), room.stream(), room.stream()
    a.push(0.0, pose)
    a.push(0.1, turned)
    c.push(0.05, turned)
    c.push(0.15, pose)
    for t in (0.0, 0.07, 0.1, 0.12, 0.2):
        numpy_frame, compiled = both(room, t, list(PAIRS))
        assert compiled.poses["soa"].shape == (2, 7)
        assert_same(numpy_frame, compiled, f"at {t}")


def test_a_room_that_grows_and_shrinks_between_frames() -> None:
    """The compiled renderer holds the room's arrays: rows added past their size
    (the arrays reallocated) and rows released give the numpy path's frames."""
    if accel.compiled() is None:
        pytest.skip(f"the render kernels are not built here: {accel.IMPLEMENTATION}")
    rng = np.random.default_rng(10)
    room = RoomBuffers(capacity=8, streams=2)
    bufs: list[StreamBuffer] = []
    for step in range(12):
        if step < 7 or step % 2:  # 2 rows of room at first: they double, twice
            buf = room.stream()
            for k in range(6):
                q = rng.normal(size=4)
                pose = np.concatenate([rng.normal(size=3), q / np.linalg.norm(q)])
                buf.push(0.05 * k + 0.01 * step, pose.astype(np.float32))
            bufs.append(buf)
        else:
            room.release(bufs.pop(int(rng.integers(len(bufs)))))
        for t in (0.02, 0.11, 0.3):
            numpy_frame, compiled = both(room, t, list(PAIRS))
            assert compiled.poses["soa"].shape == (len(bufs), 7)
            assert_same(numpy_frame, compiled, f"step {step} at {t}")


def test_the_renderer_refuses_what_does_not_fit() -> None:
    ck = accel.compiled()
    if ck is None:
        pytest.skip(f"the render kernels are not built here: {accel.IMPLEMENTATION}")
    room = RoomBuffers(capacity=4, streams=2)
    room.stream().push(0.0, np.array([0, 0, 0, 1, 0, 0, 0], np.float32))
    lo, hi, s = room.brackets
    r = ck.Renderer(
        room.times.reshape(-1), room.base, room.newest, lo, hi, s, room.pose_rows.reshape(-1, 7)
    )
    out, stalled = np.empty((1, 1, 7)), np.empty(1, dtype=bool)
    assert r.render(1, 0.0, (0,), out, stalled) in (True, False)
    np.testing.assert_array_equal(out[0, 0], [0, 0, 0, 1, 0, 0, 0])
    with pytest.raises(ValueError, match="n must be in"):
        r.render(3, 0.0, (0,), out, stalled)
    with pytest.raises(ValueError, match="no keyframes"):  # row 1 is empty
        r.render(2, 0.0, (0,), np.empty((1, 2, 7)), np.empty(2, dtype=bool))
    with pytest.raises(ValueError, match="out"):
        r.render(1, 0.0, (0, 1), out, stalled)
    with pytest.raises(TypeError, match="poses"):
        ck.Renderer(room.times.reshape(-1), room.base, room.newest, lo, hi, s, room.pose_rows)
