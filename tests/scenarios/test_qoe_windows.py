"""Window interpolators of any size in the QoE path: arrived neighbours and look-ahead delay.

The probes (``tests/window_probe.py``, 2/2 and 0/3 neighbours) return a known
function of their whole window. A direct per-query loop applies DESIGN.md's
rule (only keyframes arrived by ``tau + D``) and the registry's rule for missing
neighbours; :func:`scenarios.qoe.playout_brackets`, :func:`render_playout` and
:func:`evaluate_group` must agree with it.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from numpy.typing import NDArray
from window_probe import Probe, expected, probes  # noqa: F401

from posecast import interp
from posecast.scenarios.qoe import (
    KeyframeLog,
    evaluate_group,
    ideal_delay,
    playout_brackets,
    render_playout,
    sample_keyframes,
    window_depth,
)
from posecast.scenarios.traces import Trace

F64 = NDArray[np.float64]


def loop_play(
    capture: F64, arrival: F64, tau: float, d: float, lb: int, la: int
) -> tuple[list[int], bool] | None:
    """The window of ``tau`` and whether it stalls; None if nothing has arrived."""
    k = len(capture)
    arrived = [i for i in range(k) if arrival[i] <= tau + d]
    if not arrived:
        return None
    below = [i for i in arrived if capture[i] <= tau]
    above = [i for i in arrived if capture[i] > tau]
    stall = False
    if below and capture[below[-1]] == tau:
        lo = hi = below[-1]
    elif below and above:
        lo, hi = below[-1], above[0]
    else:
        lo = hi = max(arrived)
        stall = True
    older = [i for i in reversed(arrived) if i < lo]  # nearest first
    before = [older[j] if j < len(older) else (older[-1] if older else lo) for j in range(lb)]
    newer = [] if stall else [i for i in arrived if i > hi]
    after = [newer[j] if j < len(newer) else (newer[-1] if newer else hi) for j in range(la)]
    return [*reversed(before), lo, hi, *after], stall


def jittered_log(seed: int = 1, k: int = 14, streams: int = 2) -> KeyframeLog:
    rng = np.random.default_rng(seed)
    capture = np.cumsum(rng.uniform(0.08, 0.12, k))
    arrival = capture + rng.uniform(0.01, 0.05, k)
    arrival[4] += 0.3  # very late: reordered past several newer keyframes
    arrival[9] += 0.12
    pos = rng.uniform(-1.0, 1.0, (k, streams, 3))
    q = rng.normal(size=(k, streams, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return KeyframeLog(capture, arrival, np.concatenate([pos, q], axis=-1))


def test_window_depth_covers_every_method(probes: dict[str, Probe]) -> None:  # noqa: F811
    """The playout gathers the widest window of the methods (at least one each side)."""
    assert window_depth(["soa"]) == (1, 1)
    assert window_depth(["motor-cubic", "probe-0-3"]) == (1, 3)
    assert window_depth(["probe-2-2", "probe-0-3", "motor-quintic"]) == (2, 3)


@pytest.mark.parametrize("delay", [0.06, 0.15, 0.4])
def test_playout_gathers_arrived_neighbours_like_a_loop(delay: float) -> None:
    """playout_brackets' bracket, stall and neighbours equal the per-query loop's."""
    log = jittered_log()
    taus = np.arange(log.capture[0] - 0.05, log.capture[-1] + 0.1, 0.0037)
    taus = np.sort(np.concatenate([taus, log.capture]))
    play = playout_brackets(log.capture, log.arrival, taus, delay, lookbehind=3, lookahead=3)
    assert play.before is not None and play.after is not None
    assert play.before.shape == (taus.size, 3) and play.after.shape == (taus.size, 3)
    np.testing.assert_array_equal(play.before[:, -1], play.prev)
    np.testing.assert_array_equal(play.after[:, 0], play.nxt)
    seen_gap = False
    for i, tau in enumerate(taus):
        got = loop_play(log.capture, log.arrival, float(tau), delay, 3, 3)
        assert play.missing[i] == (got is None)
        if got is None:
            continue
        win, stall = got
        assert play.stall[i] == stall
        assert [*play.before[i], play.lo[i], play.hi[i], *play.after[i]] == win, tau
        seen_gap |= any(b - a > 1 for a, b in itertools.pairwise(win))
    assert seen_gap  # some window skipped a keyframe that had not arrived


@pytest.mark.parametrize("delay", [0.06, 0.15])
def test_render_playout_windows_match_a_loop(probes: dict[str, Probe], delay: float) -> None:  # noqa: F811
    """Both probes, rendered from one playout in one batched call each, equal the loop."""
    log = jittered_log()
    taus = np.arange(log.capture[0] - 0.05, log.capture[-1] + 0.1, 0.0041)
    lb, la = window_depth(list(probes))
    play = playout_brackets(log.capture, log.arrival, taus, delay, lookbehind=lb, lookahead=la)
    for name, probe in probes.items():
        ren = render_playout(log, taus, play, name)
        shown = np.flatnonzero(ren.shown)
        assert len(probe.calls) == 1 and probe.calls[0][0][:2] == (shown.size, 2)
        for row, i in enumerate(shown):
            got = loop_play(
                log.capture, log.arrival, float(taus[i]), delay, probe.lookbehind, probe.lookahead
            )
            assert got is not None
            win, stall = got
            t = float(taus[i]) if not stall else float(log.capture[win[probe.lookbehind]])
            for s in range(2):
                want = expected(probe, log.poses[:, s], log.capture, win, t)
                np.testing.assert_allclose(ren.poses[row, s], want, rtol=0, atol=1e-12)


def test_render_refuses_a_playout_narrower_than_the_window(probes: dict[str, Probe]) -> None:  # noqa: F811
    """A playout gathered for one neighbour cannot serve a 2-keyframe look-behind."""
    log = jittered_log()
    taus = log.capture[2:5] + 0.01
    play = playout_brackets(log.capture, log.arrival, taus, 0.5)
    with pytest.raises(ValueError, match="needs 2 keyframe"):
        render_playout(log, taus, play, "probe-2-2")


def test_evaluate_group_mixes_window_sizes(probes: dict[str, Probe]) -> None:  # noqa: F811
    """One group with 1/1, 2/2 and 0/3 methods: each scored on its own window."""
    log = jittered_log()
    rng = np.random.default_rng(3)
    t = np.arange(log.capture[0], log.capture[-1], 1 / 90)
    truth_poses = np.concatenate([rng.uniform(-1, 1, (t.size, 2, 3)), np.zeros((t.size, 2, 4))], -1)
    truth_poses[..., 3] = 1.0
    truth = Trace("jitter", t, truth_poses, ("left", "right"))
    d = 0.15
    methods = ["motor-cubic", "probe-2-2", "probe-0-3"]
    res = evaluate_group(truth, log, d, methods)
    alone = evaluate_group(truth, log, d, ["motor-cubic"])
    np.testing.assert_array_equal(
        np.concatenate(res["motor-cubic"]["hands"].pos_mm),
        np.concatenate(alone["motor-cubic"]["hands"].pos_mm),
    )
    for name in ("probe-2-2", "probe-0-3"):
        probe = probes[name]
        want = []
        for i, tau in enumerate(t):
            got = loop_play(
                log.capture, log.arrival, float(tau), d, probe.lookbehind, probe.lookahead
            )
            if got is None:
                continue
            win, stall = got
            tq = float(tau) if not stall else float(log.capture[win[probe.lookbehind]])
            rendered = expected(probe, log.poses[:, 0], log.capture, win, tq)
            want.append(1000.0 * np.linalg.norm(rendered[:3] - truth_poses[i, 0, :3]))
        got_mm = res[name]["hands"].pos_mm[0]  # stream 0 ("left")
        np.testing.assert_allclose(got_mm, want, rtol=1e-12, atol=1e-9)


def _native_trace(rate: float = 90.0, seconds: float = 2.0) -> Trace:
    t = np.arange(0.0, seconds, 1.0 / rate)
    poses = np.zeros((t.size, 1, 7))
    poses[:, 0, 0] = np.sin(3 * t)
    poses[:, 0, 1] = t * t
    poses[:, 0, 3] = np.cos(t)
    poses[:, 0, 5] = np.sin(t)
    return Trace("native", t, poses, ("right",))


@pytest.mark.parametrize("name", ["probe-0-3", "probe-2-2", "motor-quintic"])
def test_ideal_delay_pays_for_every_lookahead_keyframe(
    probes: dict[str, Probe],  # noqa: F811
    name: str,
) -> None:
    """Ideal link, D = ideal_delay(rate, native, lookahead): no stalls, every window complete.

    The rendering then equals the offline track evaluator's; one interval less
    leaves the last look-ahead keyframe missing for some queries.
    """
    tr = _native_trace()
    rate = 10.0
    la = interp.info(name).lookahead
    lb = interp.info(name).lookbehind
    send, idx = sample_keyframes(tr.times, rate)
    log = KeyframeLog(tr.times[idx], send, tr.poses[idx])
    k = log.capture.size
    taus = tr.times[(tr.times >= log.capture[0]) & (tr.times <= log.capture[-1])]
    d = ideal_delay(rate, tr.native_rate, la)
    assert d == pytest.approx((1 + la) / rate + 1 / 90)
    play = playout_brackets(log.capture, log.arrival, taus, d, lookbehind=max(lb, 1), lookahead=la)
    assert not play.stall.any()
    assert play.after is not None
    inside = play.hi > play.lo
    _, complete = interp.window_indices(play.lo, play.hi, k, 0, la)
    np.testing.assert_array_equal(play.after[inside], complete[inside])
    ren = render_playout(log, taus, play, name)
    offline = interp.evaluate_track(log.capture, log.poses, taus, name)
    np.testing.assert_array_equal(ren.poses, offline.poses)
    short = playout_brackets(
        log.capture, log.arrival, taus, ideal_delay(rate, tr.native_rate, la - 1), lookahead=la
    )
    assert short.after is not None and not short.stall.any()
    assert np.any(short.after[inside, la - 1] != complete[inside, la - 1])
