"""The live receiver's render path with window interpolators of any size.

:func:`client.render.render_buffers` gathers each buffer's window (the
widest among the methods) and makes one batched call per method; a direct
per-buffer loop applying the registry's rule for missing neighbours (buffer
ends; everything after a stalled, held bracket) says what it must return.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from window_probe import Probe, expected, probes  # noqa: F401

from posecast import interp
from posecast.client.buffers import StreamBuffer
from posecast.client.render import render_buffers

F64 = NDArray[np.float64]


def loop_window(times: list[float], t: float, lb: int, la: int) -> tuple[list[int], bool]:
    """A buffer's window at playout time ``t`` and whether it stalls, one rule at a time."""
    n = len(times)
    below = [i for i in range(n) if times[i] <= t]
    if not below:
        lo = hi = n - 1  # before the first keyframe: hold the newest
        stall = True
    elif times[below[-1]] == t:
        lo = hi = below[-1]
        stall = False
    elif below[-1] == n - 1:
        lo = hi = n - 1
        stall = True
    else:
        lo, hi, stall = below[-1], below[-1] + 1, False
    before = [max(lo - j, 0) for j in range(lb, 0, -1)]
    after = [min(hi + j, n - 1) if hi > lo else hi for j in range(1, la + 1)]
    return [*before, lo, hi, *after], stall


def filled_buffers(seed: int = 0) -> list[StreamBuffer]:
    """Buffers of 1, 3 and 12 keyframes at different times, pushed out of order."""
    rng = np.random.default_rng(seed)
    bufs = []
    for j, n in enumerate((1, 3, 12)):
        buf = StreamBuffer()
        times = 0.02 * j + np.cumsum(rng.uniform(0.08, 0.12, n))
        for i in rng.permutation(n):
            q = rng.normal(size=4)
            pose = np.concatenate([rng.uniform(-1, 1, 3), q / np.linalg.norm(q)])
            assert buf.push(float(times[i]), pose.astype(np.float32))
        bufs.append(buf)
    return bufs


def test_render_buffers_gathers_any_window_in_one_call_per_method(
    probes: dict[str, Probe],  # noqa: F811
) -> None:
    """Every method, every buffer, at the ends, inside and past the buffers: equals the loop."""
    bufs = filled_buffers()
    methods = ["soa", "motor-cubic", "motor-quintic", *probes]
    last = max(b.times[-1] for b in bufs)
    checked = 0
    for t in np.arange(0.0, last + 0.1, 0.013):
        calls_before = {name: len(p.calls) for name, p in probes.items()}
        frame = render_buffers(bufs, float(t), methods)
        for name, probe in probes.items():
            assert len(probe.calls) == calls_before[name] + 1
            assert probe.calls[-1][0] == (1, len(bufs), probe.size, 7)
        for j, buf in enumerate(bufs):
            poses = np.asarray(buf.poses, dtype=np.float64)
            times = np.asarray(buf.times)
            for name, probe in probes.items():
                win, stall = loop_window(buf.times, float(t), probe.lookbehind, probe.lookahead)
                assert frame.stalled[j] == stall
                tq = float(t) if not stall else buf.times[win[probe.lookbehind]]
                want = expected(probe, poses, times, win, tq)
                np.testing.assert_allclose(frame.poses[name][j], want, rtol=0, atol=1e-12)
            for name, lb, la in (("motor-cubic", 1, 1), ("motor-quintic", 2, 2)):
                win, stall = loop_window(buf.times, float(t), lb, la)
                tq = float(t) if not stall else buf.times[win[lb]]
                want = interp.get(name)(poses[win], times[win], tq)
                np.testing.assert_array_equal(frame.poses[name][j], want)
            checked += 1
    assert checked > 100


def test_render_buffers_matches_the_offline_evaluator_inside_the_buffer() -> None:
    """Inside a full buffer the live render equals evaluate_track on the same keyframes."""
    buf = filled_buffers(seed=2)[2]
    poses = np.asarray(buf.poses, dtype=np.float64)
    times = np.asarray(buf.times)
    query = np.linspace(times[0] + 1e-3, times[-1] - 1e-3, 37)
    offline = interp.evaluate_track(times, poses, query, "motor-quintic").poses[:, 0]
    for i, t in enumerate(query):
        frame = render_buffers([buf], float(t), ["motor-quintic"])
        np.testing.assert_array_equal(frame.poses["motor-quintic"][0], offline[i])
