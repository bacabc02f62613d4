"""The receiver's buffers keep keyframe velocities; render_buffers renders velocity methods.

Velocity interpolators (``motor-hermite``) render from the velocity that came
with each keyframe. The live receiver must show what the QoE definition says
(:mod:`scenarios.qoe`: ``playout_brackets`` + ``render_playout`` /
``evaluate_group`` on a :class:`~scenarios.qoe.KeyframeLog` with velocities).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray

from posecast import interp
from posecast.client.buffers import StreamBuffer
from posecast.client.render import VELOCITY_FALLBACK, render_buffers, rendered_method
from posecast.scenarios.qoe import KeyframeLog, evaluate_group, playout_brackets, render_playout
from posecast.scenarios.traces import DEVICE_NAMES, Trace, load_trace

F64 = NDArray[np.float64]


def _pose(x: float) -> NDArray[np.float32]:
    return np.array([x, 0, 0, 1, 0, 0, 0], dtype=np.float32)


def _random_pose(rng: np.random.Generator) -> NDArray[np.float32]:
    q = rng.normal(size=4)
    return np.r_[rng.normal(size=3), q / np.linalg.norm(q)].astype(np.float32)


def test_buffer_keeps_velocities_with_their_keyframes() -> None:
    """Out of order, duplicates, stale frames and eviction keep velocities aligned."""
    buf = StreamBuffer(capacity=4)
    for t in (1.0, 3.0, 2.0, 3.0, 5.0, 4.0, 6.0, 0.5):
        buf.push(t, _pose(t), velocity=np.full(6, t))
    assert buf.times == [3.0, 4.0, 5.0, 6.0]
    assert [float(v[0]) for v in buf.velocities] == buf.times
    assert (buf.duplicates, buf.evicted, buf.stale) == (1, 2, 1)
    assert not buf.push(4.5, _pose(4.5), floor=5.5, velocity=np.ones(6))  # superseded
    assert buf.push(4.5, _pose(4.5), floor=4.2, velocity=np.full(6, 4.5))  # late lower bracket
    assert [float(v[0]) for v in buf.velocities] == buf.times == [4.0, 4.5, 5.0, 6.0]
    assert buf.push(7.0, _pose(7.0))  # no velocity: zeros
    assert buf.velocities[-1].tolist() == [0.0] * 6
    assert len(buf.velocities) == len(buf.poses) == len(buf.times) == 4


def test_buffer_without_velocities_keeps_its_old_behaviour() -> None:
    """Positional pushes (the pre-velocity API) still work; velocities are zeros."""
    buf = StreamBuffer(capacity=3)
    assert buf.push(0.2, _pose(2), -np.inf)
    assert buf.push(0.1, _pose(1))
    assert not buf.push(0.05, _pose(0), 0.15)
    assert buf.times == [0.1, 0.2]
    assert all(not v.any() for v in buf.velocities)


def test_render_buffers_renders_velocity_methods_on_the_bracket() -> None:
    """One batched call per method; hermite uses each bracket's buffered velocities."""
    rng = np.random.default_rng(1)
    bufs = [StreamBuffer() for _ in range(3)]
    for j, buf in enumerate(bufs):
        for k in range(5):
            buf.push(0.1 * k + 0.01 * j, _random_pose(rng), velocity=rng.normal(size=6))
    hermite = interp.get("motor-hermite")
    methods = ["soa", "motor-hermite", "motor-cubic"]
    t = 0.215
    frame = render_buffers(bufs, t, methods)
    alone = {m: render_buffers(bufs, t, [m]).poses[m] for m in methods}
    assert not frame.stalled.any()
    for j, buf in enumerate(bufs):
        lo, hi, s, stall = buf.bracket(t)
        assert not stall and hi == lo + 1
        dt = buf.times[hi] - buf.times[lo]
        want = hermite(buf.poses[lo], buf.poses[hi], buf.velocities[lo], buf.velocities[hi], dt, s)
        np.testing.assert_allclose(frame.poses["motor-hermite"][j], want, rtol=0, atol=1e-12)
        # Velocities matter: with zero velocities hermite renders something else.
        flat = hermite(buf.poses[lo], buf.poses[hi], np.zeros(6), np.zeros(6), dt, s)
        assert np.abs(flat - want).max() > 1e-3
    for m in methods:  # the velocity method does not change the others' windows
        np.testing.assert_array_equal(frame.poses[m], alone[m])


def test_render_buffers_holds_velocity_methods_on_a_stall() -> None:
    """Past the newest keyframe, before the first, and on a keyframe: the keyframe itself."""
    rng = np.random.default_rng(2)
    bufs = [StreamBuffer() for _ in range(2)]
    for buf in bufs:
        for k in range(3):
            buf.push(0.1 * k, _random_pose(rng), velocity=rng.normal(size=6))
    for t, stalled, row in ((9.0, True, -1), (-1.0, True, -1), (0.1, False, 1)):
        frame = render_buffers([*bufs, StreamBuffer()], t, ["motor-hermite", "soa"])
        assert frame.stalled.tolist() == [stalled, stalled]
        for j, buf in enumerate(bufs):
            for m in ("motor-hermite", "soa"):
                np.testing.assert_allclose(frame.poses[m][j], buf.poses[row], atol=1e-7)
    empty = render_buffers([StreamBuffer()], 1.0, ["motor-hermite"])
    assert empty.poses["motor-hermite"].shape == (0, 7) and empty.stalled.shape == (0,)


def _arrival_log(trace_path: Path, rate: float, seed: int) -> tuple[Trace, KeyframeLog]:
    """The truth, and its keyframes at ``rate`` with jittered, reordered arrivals.

    Poses are float32 and velocities float16, as the wire carries them, so the
    offline log and the live buffers hold the same numbers.
    """
    trace = load_trace(trace_path).select(DEVICE_NAMES).window(20.0, 26.0)
    rng = np.random.default_rng(seed)
    send = np.arange(trace.times[0], trace.times[-1], 1.0 / rate)
    idx = np.unique(np.searchsorted(trace.times, send, side="right") - 1)
    capture = trace.times[idx]
    # 20-140 ms on the way: often later than the next keyframe (reordering).
    arrival = capture + rng.uniform(0.02, 0.14, capture.size)
    poses = trace.poses[idx].astype(np.float32).astype(np.float64)
    vel = trace.causal_velocities()[idx].astype(np.float16).astype(np.float64)
    return trace, KeyframeLog(capture, arrival, poses, vel)


def _live_render(
    log: KeyframeLog, taus: F64, delay: float, methods: list[str]
) -> tuple[dict[str, list[F64]], list[NDArray[np.bool_]], list[int]]:
    """A receiver showing each ``tau`` at time ``tau + delay``; keyframes pushed on arrival."""
    n_streams = log.poses.shape[1]
    assert log.velocities is not None
    vel = log.velocities
    bufs = [StreamBuffer() for _ in range(n_streams)]
    order = np.argsort(log.arrival, kind="stable")
    nxt = 0
    floor = -np.inf
    out: dict[str, list[F64]] = {m: [] for m in methods}
    stalls: list[NDArray[np.bool_]] = []
    shown: list[int] = []
    for q, tau in enumerate(taus):
        while nxt < order.size and log.arrival[order[nxt]] <= tau + delay:
            k = order[nxt]
            for j, buf in enumerate(bufs):
                pose = log.poses[k, j].astype(np.float32)
                buf.push(float(log.capture[k]), pose, floor, vel[k, j])
            nxt += 1
        frame = render_buffers(bufs, float(tau), methods)
        floor = float(tau)
        if frame.stalled.size:
            assert frame.stalled.size == n_streams
            shown.append(q)
            stalls.append(frame.stalled)
            for m in methods:
                out[m].append(frame.poses[m])
    return out, stalls, shown


@pytest.mark.parametrize("seed", [0, 1])
def test_live_velocity_render_equals_the_offline_qoe_path(dev_trace_path: Path, seed: int) -> None:
    """Each live frame is render_playout's pose; its errors are evaluate_group's."""
    rate, delay = 15.0, 1.0 / 15.0 + 0.06
    methods = ["soa", "motor-hermite"]
    truth, log = _arrival_log(dev_trace_path, rate, seed)
    window = (float(log.capture[0]), float(log.capture[-1]))
    inside = np.flatnonzero((truth.times >= window[0]) & (truth.times <= window[1]))
    taus = truth.times[inside]
    live, stalls, shown = _live_render(log, taus, delay, methods)
    play = playout_brackets(log.capture, log.arrival, taus, delay)
    assert shown == np.flatnonzero(~play.missing).tolist()
    live_stall = np.array([s[0] for s in stalls])
    assert all((s == s[0]).all() for s in stalls)  # one sender: its streams stall together
    np.testing.assert_array_equal(live_stall, play.stall[~play.missing])
    assert 0 < live_stall.sum() < live_stall.size / 2  # both regimes are exercised
    for m in methods:
        offline = render_playout(log, taus, play, m).poses
        np.testing.assert_allclose(np.array(live[m]), offline, rtol=0, atol=1e-9)
    # The QoE numbers of these frames are evaluate_group's, sample for sample.
    res = evaluate_group(truth, log, delay, methods, window)
    true_shown = truth.poses[inside[shown]]
    for m in methods:
        tip = interp.tip_error_mm(np.array(live[m]), true_shown)
        got = np.concatenate([res[m]["hands"].tip_mm[0], res[m]["hands"].tip_mm[1]])
        want = np.concatenate([tip[:, 1], tip[:, 2]])
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)
    # Velocities pay off where the keyframes bracket the sample.
    hands = [res[m]["hands"].stats()["tip_p50_mm"] for m in methods]
    assert hands[1] < hands[0]


def test_velocity_methods_render_streams_without_velocities_with_the_fallback() -> None:
    """In one batch: a stream whose sender reports velocities gets motor-hermite, one
    whose sender reports none gets motor-lerp (not a Hermite curve through zeros)."""
    rng = np.random.default_rng(5)
    times = [0.0, 0.1, 0.2]
    poses = np.zeros((3, 7), dtype=np.float32)
    poses[:, :3] = rng.normal(size=(3, 3))
    q = rng.normal(size=(3, 4))
    poses[:, 3:] = q / np.linalg.norm(q, axis=1, keepdims=True)
    vels = rng.normal(size=(3, 6))
    with_v = StreamBuffer()
    without = StreamBuffer(has_velocities=False)
    for t, p, v in zip(times, poses, vels, strict=True):
        with_v.push(t, p, velocity=v)
        without.push(t, p)
    methods = ["soa", "motor-hermite"]
    frame = render_buffers([with_v, without], 0.13, methods).poses
    k = poses[:, None].astype(np.float64)
    lo, hi, s = np.array([[1]]), np.array([[2]]), np.array([[0.3]])
    t = np.array(times)
    hermite = interp.interpolate_brackets(
        k, lo, hi, s, "motor-hermite", times=t, velocities=vels[:, None]
    )[0, 0]
    lerp = interp.interpolate_brackets(k, lo, hi, s, VELOCITY_FALLBACK, times=t)[0, 0]
    np.testing.assert_allclose(frame["motor-hermite"][0], hermite, atol=1e-12)
    np.testing.assert_allclose(frame["motor-hermite"][1], lerp, atol=1e-12)
    assert np.abs(hermite - lerp).max() > 1e-3  # the two really differ here
    np.testing.assert_allclose(frame["soa"][0], frame["soa"][1], atol=1e-12)
    assert rendered_method("motor-hermite", False) == VELOCITY_FALLBACK
    assert rendered_method("motor-hermite", True) == "motor-hermite"
    assert rendered_method("soa", False) == "soa"
