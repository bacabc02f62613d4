"""Table 1 and its error-versus-latency view with a 6-keyframe window method.

The frontier sweep reuses renders whose bracket and neighbours match the
all-arrived reference (``scenarios.table1._same_bracket``); with two keyframes of
look-ahead and small playout delays the far neighbours are often missing, so
every point must still equal what :func:`scenarios.qoe.evaluate_group` gives.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from posecast.interp import window_indices
from posecast.scenarios.qoe import evaluate_group, playout_brackets, summarize
from posecast.scenarios.table1 import _ideal_log, keyframe_velocities, run_table1
from posecast.scenarios.traces import Trace, load_trace


@pytest.fixture(scope="module")
def quintic_run(dev_trace_path: Path) -> dict[str, object]:
    trace = load_trace(dev_trace_path).window(30.0, 38.0)
    report = run_table1(
        [trace],
        rates=[10, 20],
        methods=["motor-cubic", "motor-quintic"],
        bench=False,
        link=False,
        plots=False,
        frontier_rates=[10, 20],
        frontier_fractions=(0.25, 1.0),
    )
    return {"report": report, "trace": trace}


def test_table1_plays_out_two_lookahead_intervals(quintic_run: dict[str, object]) -> None:
    """motor-quintic's look-ahead is 2 and its ideal playout delay two intervals more than SoA's."""
    report = quintic_run["report"]
    assert isinstance(report, dict)
    assert report["config"]["lookahead"] == {"soa": 0, "motor-cubic": 1, "motor-quintic": 2}
    points = report["frontier"]["points"]
    quintic = [p for p in points if p["method"] == "motor-quintic"]
    assert quintic and all(p["lookahead"] == 2 for p in quintic)


@pytest.mark.parametrize("method", ["motor-cubic", "motor-quintic"])
@pytest.mark.parametrize("variant", ["hold", "extrapolate"])
def test_window_frontier_points_equal_evaluate_group(
    quintic_run: dict[str, object], method: str, variant: str
) -> None:
    """Each ideal-network point equals evaluate_group with the same D, partial windows included."""
    report = quintic_run["report"]
    trace = quintic_run["trace"]
    assert isinstance(report, dict) and isinstance(trace, Trace)
    cfg = report["frontier"]["config"]
    hands = trace.select(["left", "right"])
    vel = keyframe_velocities(trace)[:, 1:]
    checked = 0
    for p in report["frontier"]["points"]:
        if not (p["network"] == "ideal" and p["method"] == method and p["variant"] == variant):
            continue
        log, d1, window, _ = _ideal_log(0, hands, p["rate"], 0, vel)
        d = d1 - 1.0 / p["rate"] + (p["fraction"] + p["lookahead"]) / p["rate"]
        g = evaluate_group(
            hands,
            log,
            d,
            [method],
            window,
            extrapolate_horizon=None if variant == "hold" else cfg["extrapolate_horizon_s"],
            correction_time=0.0,
            extrapolate_mode="auto",
        )
        st = summarize([g], extrapolation=True)[method]["hands"]
        assert p["headline_mm"] == pytest.approx(st["tip_p95_mm"], rel=1e-9, abs=1e-5)
        assert p["stall_fraction"] == pytest.approx(st["stall_fraction"], abs=1e-5)
        checked += 1
    assert checked >= 4  # 2 rates x 2 fractions, plus the rates bisected in between


def test_small_delays_leave_the_far_lookahead_keyframe_out(quintic_run: dict[str, object]) -> None:
    """At f = 0.25 the second look-ahead keyframe has often not arrived: partial windows."""
    trace = quintic_run["trace"]
    assert isinstance(trace, Trace)
    hands = trace.select(["left", "right"])
    log, d1, window, _ = _ideal_log(0, hands, 20, 0, None)
    taus = hands.times[(hands.times >= window[0]) & (hands.times <= window[1])]
    d = d1 - 1.0 / 20 + (0.25 + 2) / 20
    play = playout_brackets(log.capture, log.arrival, taus, d, lookbehind=2, lookahead=2)
    assert play.after is not None and not play.stall.any()
    _, complete = window_indices(play.lo, play.hi, log.capture.size, 0, 2)
    inside = play.hi > play.lo
    partial = (play.after[:, 1] != complete[:, 1]) & inside
    assert 0.1 < partial.mean() < 0.9
