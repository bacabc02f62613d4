"""One preallocated array per room: RoomBuffers, and the vectorised render frame.

:class:`client.buffers.RoomBuffers` keeps every remote stream's keyframes
in one row of a few arrays; each :class:`~client.buffers.StreamBuffer`'s
lists mirror its row. :func:`~client.render.render_buffers` brackets every
row at once and gathers with one ``take`` per side. The render frame must show
exactly what the former per-buffer path showed (a Python loop: bisect each
buffer, gather lists, one ``interp.interpolate_brackets`` per method, kept
here as the reference) on real motion: trace slices of the bundled sample,
keyframes arriving late, out of order and twice, buffers evicting, playout
times before, between, on and after the keyframes.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import cache

import numpy as np
import pytest
from numpy.typing import NDArray

from posecast import interp
from posecast.client.buffers import RoomBuffers, StreamBuffer
from posecast.client.render import render_buffers, rendered_method
from posecast.scenarios.qoe import window_depth
from posecast.scenarios.traces import Trace, find_traces, load_trace

F64 = NDArray[np.float64]

METHODS = ("soa", "dq-slerp", "motor-lerp", "motor-cubic", "motor-quintic", "motor-hermite")


def former_render(
    buffers: Sequence[StreamBuffer], t: float, methods: Sequence[str]
) -> tuple[dict[str, F64], NDArray[np.bool_]]:
    """The render path before RoomBuffers, one buffer at a time (the reference)."""
    live = [b for b in buffers if len(b)]
    n = len(live)
    lb, la = window_depth(methods)
    k = lb + 2 + la
    flat_poses, flat_times, flat_vels = [], [], []
    s = np.empty((1, n))
    stalled = np.zeros(n, dtype=bool)
    for j, buf in enumerate(live):
        lo, hi, frac, stall = buf.bracket(t)
        last = len(buf) - 1
        rows = [max(lo - i, 0) for i in range(lb, 0, -1)]
        rows += [lo, hi]
        rows += [min(hi + i, last) if hi > lo else hi for i in range(1, la + 1)]
        flat_poses += [buf.poses[i] for i in rows]
        flat_times += [buf.times[i] for i in rows]
        flat_vels += [buf.velocities[i] for i in rows]
        s[0, j], stalled[j] = frac, stall
    keys = np.array(flat_poses, dtype=np.float64).reshape(n, k, 7).transpose(1, 0, 2)
    times = np.array(flat_times, dtype=np.float64).reshape(n, k).T
    vel = np.array(flat_vels, dtype=np.float64).reshape(n, k, 6).transpose(1, 0, 2)
    lo_idx = np.full((1, n), lb, dtype=np.intp)
    before = np.broadcast_to(np.arange(lb, dtype=np.intp)[:, None], (lb, n)).T[None]
    after = np.broadcast_to(np.arange(lb + 2, k, dtype=np.intp)[:, None], (la, n)).T[None]
    no_velocity = np.array([not b.has_velocities for b in live])
    shown = {m: rendered_method(m, not no_velocity.any()) for m in methods}
    out = {
        name: interp.interpolate_brackets(
            keys,
            lo_idx,
            lo_idx + 1,
            s,
            name,
            times=times,
            velocities=vel,
            before=before,
            after=after,
        )[0]
        for name in dict.fromkeys([*methods, *shown.values()])
    }
    frame = {
        m: out[m] if shown[m] == m else np.where(no_velocity[:, None], out[shown[m]], out[m])
        for m in methods
    }
    return frame, stalled


@cache
def sample_motion() -> tuple[tuple[Trace, F64], ...]:
    """The bundled sample traces, each with its causal velocities ``(N, S, 6)``: read
    and fitted once per process (the fit over a whole trace is most of a room's cost),
    shared read-only."""
    out = []
    for tr in map(load_trace, find_traces("traces:sample")):
        velocities = tr.causal_velocities()
        for a in (tr.times, tr.poses, velocities):
            a.setflags(write=False)
        out.append((tr, velocities))
    return tuple(out)


def trace_room(
    streams: int, rate: float = 15.0, capacity: int = 12, seed: int = 0
) -> tuple[RoomBuffers, list[StreamBuffer], float, float]:
    """``streams`` remote streams of real motion, keyframes at ``rate`` arriving badly.

    Each stream is one device of a bundled trace from its own start offset; every
    third sender reports no velocities. Keyframes arrive in small shuffled groups
    (late and out of order), some twice; ``capacity`` forces evictions. Returns
    the room, its buffers and the span of capture times.
    """
    rng = np.random.default_rng(seed)
    traces = sample_motion()
    room = RoomBuffers(capacity=capacity)
    bufs = []
    span = (np.inf, -np.inf)
    for j in range(streams):
        tr, velocities = traces[j % len(traces)]
        dev = j % len(tr.streams)
        vel = velocities[:, dev]
        buf = room.stream(has_velocities=j % 3 != 2)
        start = rng.uniform(0.0, 20.0)
        send = start + np.arange(0.0, 3.0, 1.0 / rate) + rng.uniform(-0.004, 0.004)
        idx = np.searchsorted(tr.times, send).clip(0, len(tr.times) - 1)
        order = np.concatenate(
            [rng.permutation(g) for g in np.array_split(np.arange(len(idx)), 12)]
        )
        for i in [*order, *rng.choice(order, 5)]:  # five arrive twice
            buf.push(
                float(tr.times[idx[i]] - start),
                tr.poses[idx[i], dev].astype(np.float32),
                velocity=vel[idx[i]],
            )
        bufs.append(buf)
        span = (min(span[0], buf.times[0]), max(span[1], buf.times[-1]))
    return room, bufs, span[0], span[1]


def test_room_rows_mirror_the_buffers() -> None:
    """Every row holds its buffer's keyframes in order, float64 poses, +inf beyond."""
    room, bufs, _, _ = trace_room(40, capacity=8)
    assert len(room) == 40 and room.counts.shape[0] >= 40  # grown from 16 rows
    for b in bufs:
        c = len(b)
        assert room.counts[b.row] == c and b.evicted > 0 and b.duplicates + b.stale > 0
        np.testing.assert_array_equal(room.times[b.row, :c], b.times)
        assert np.all(np.isinf(room.times[b.row, c:]))
        np.testing.assert_array_equal(room.poses[:, b.row, :c].T, np.asarray(b.poses, np.float64))
        np.testing.assert_array_equal(room.velocities[b.row, :c], np.asarray(b.velocities))
        assert room.has_velocities[b.row] == b.has_velocities


@pytest.mark.parametrize("methods", [("soa",), ("soa", "dq-slerp", "motor-lerp"), METHODS])
def test_render_frame_equals_the_former_path_on_trace_slices(methods: tuple[str, ...]) -> None:
    """100 streams of real motion at 45 Hz playout times: the same poses, bit for bit."""
    room, bufs, t0, t1 = trace_room(100)
    taus = [t0 - 0.1, *np.arange(t0, t1 + 0.2, 1.0 / 45.0)]
    taus += [bufs[7].times[3], bufs[7].times[-1], bufs[50].times[0]]  # exactly on keyframes
    stalls = 0
    for t in taus:
        frame = render_buffers(room, float(t), methods)
        want, stalled = former_render(bufs, float(t), methods)
        np.testing.assert_array_equal(frame.stalled, stalled)
        stalls += int(stalled.sum())
        for m in methods:
            np.testing.assert_array_equal(frame.poses[m], want[m], err_msg=f"{m} at {t}")
    assert 0 < stalls < len(taus) * 100  # both kinds of frame were checked


def test_a_list_of_buffers_renders_as_the_room() -> None:
    """The bot's room, a subset of its buffers in any order, or buffers of other rooms."""
    room, bufs, t0, t1 = trace_room(30)
    t = 0.5 * (t0 + t1)
    methods = ["soa", "motor-cubic"]
    whole = render_buffers(room, t, methods)
    listed = render_buffers(bufs, t, methods)
    picked = [bufs[i] for i in (5, 2, 29, 11)]
    subset = render_buffers(picked, t, methods)
    alone = []
    for b in picked:  # copied into rooms of their own
        c = StreamBuffer(capacity=12, has_velocities=b.has_velocities)
        for tk, p, v in zip(b.times, b.poses, b.velocities, strict=True):
            c.push(tk, p, velocity=v)
        alone.append(c)
    apart = render_buffers(alone, t, methods)
    for m in methods:
        np.testing.assert_array_equal(listed.poses[m], whole.poses[m])
        np.testing.assert_array_equal(subset.poses[m], whole.poses[m][[5, 2, 29, 11]])
        np.testing.assert_array_equal(apart.poses[m], subset.poses[m])


def test_empty_rows_are_skipped_and_an_empty_room_renders_nothing() -> None:
    """Streams with no keyframe yet are not rendered; their neighbours are."""
    room = RoomBuffers()
    assert render_buffers(room, 1.0, ["soa"]).poses["soa"].shape == (0, 7)
    a, _, c = room.stream(), room.stream(), room.stream()
    pose = np.array([0.0, 1.0, 2.0, 1.0, 0.0, 0.0, 0.0], dtype=np.float32)
    a.push(1.0, pose)
    c.push(2.0, pose)
    frame = render_buffers(room, 1.5, ["soa"])
    np.testing.assert_array_equal(frame.poses["soa"], np.tile(pose.astype(np.float64), (2, 1)))
    np.testing.assert_array_equal(frame.stalled, [True, True])  # past a's newest, before c's


def test_push_refuses_poses_that_would_break_every_render() -> None:
    """A NaN, an infinite capture time or a zero quaternion is refused and counted."""
    buf = StreamBuffer()
    good = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], dtype=np.float32)
    bad_q = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], dtype=np.float32)
    nan = good.copy()
    nan[1] = np.nan
    assert not buf.push(1.0, bad_q) and not buf.push(1.0, nan) and not buf.push(np.inf, good)
    assert buf.invalid == 3 and len(buf) == 0
    assert buf.push(1.0, good) and len(buf) == 1


def test_off_unit_quaternions_are_normalised_on_arrival() -> None:
    """The room holds unit quaternions; the buffer's list keeps what arrived."""
    buf = StreamBuffer()
    pose = np.array([1.0, 2.0, 3.0, 2.0, 0.0, 0.0, 0.0], dtype=np.float32)
    assert buf.push(0.5, pose)
    np.testing.assert_array_equal(buf.room.poses[:, buf.row, 0], [1.0, 2.0, 3.0, 1.0, 0, 0, 0])
    np.testing.assert_array_equal(buf.poses[0], pose)


def test_buffer_capacity_is_bounded_by_its_room() -> None:
    """A stream's capacity cannot exceed its room's row width; a clear error says so."""
    room = RoomBuffers(capacity=8)
    assert room.stream(capacity=4).capacity == 4
    with pytest.raises(ValueError, match=r"capacity must be in 1\.\.8"):
        room.stream(capacity=9)
    with pytest.raises(ValueError, match="capacity must be at least 1"):
        RoomBuffers(capacity=0)
