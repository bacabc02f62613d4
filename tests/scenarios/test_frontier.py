"""Error versus latency: frontier arithmetic, dead reckoning in the QoE pipeline, a real run."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from posecast.interp.extrapolate import twist_extrapolate
from posecast.scenarios.qoe import (
    EXTRAPOLATION_KEYS,
    STAT_KEYS,
    KeyframeLog,
    evaluate_group,
    playout_brackets,
    render_playout,
    sample_keyframes,
    summarize,
)
from posecast.scenarios.table1 import (
    _ideal_log,
    cheapest_point,
    keyframe_velocities,
    pareto_frontier,
    run_table1,
)
from posecast.scenarios.traces import Trace, load_trace

# --- frontier arithmetic --------------------------------------------------------------


def _pt(lat: float, head: float, bw: float = 1.0, method: str = "m") -> dict[str, Any]:
    return {"latency_ms": lat, "headline_mm": head, "bytes_per_s": bw, "method": method}


def test_frontier_keeps_only_undominated_points_in_latency_order() -> None:
    """A point survives only if it beats every point at equal or lower latency."""
    pts = [_pt(50, 30), _pt(40, 60), _pt(60, 35), _pt(70, 20), _pt(40, 50), _pt(80, 20)]
    got = [(p["latency_ms"], p["headline_mm"]) for p in pareto_frontier(pts)]
    assert got == [(40, 50), (50, 30), (70, 20)]


def test_frontier_skips_missing_and_non_finite_values() -> None:
    """NaN, infinite or missing numbers never enter the frontier."""
    pts: list[dict[str, Any]] = [_pt(10, math.nan), _pt(math.inf, 1), {"latency_ms": 5}, _pt(20, 9)]
    assert [p["latency_ms"] for p in pareto_frontier(pts)] == [20]
    assert pareto_frontier([]) == []


def test_frontier_is_the_best_headline_within_each_budget() -> None:
    """Reading the frontier as a step function gives min headline over latency <= budget."""
    rng = np.random.default_rng(1)
    pts = [_pt(float(a), float(b)) for a, b in rng.uniform(0, 100, (200, 2))]
    front = pareto_frontier(pts)
    for budget in np.linspace(0, 100, 37):
        inside = [p["headline_mm"] for p in pts if p["latency_ms"] <= budget]
        steps = [p["headline_mm"] for p in front if p["latency_ms"] <= budget]
        assert (min(inside) if inside else None) == (steps[-1] if steps else None)


def test_cheapest_point_respects_latency_quality_and_methods() -> None:
    """Fewest bytes/s at no more latency and error; ties to lower latency; None if none."""
    pts = [
        _pt(40, 10, 900, "a"),
        _pt(45, 10, 500, "b"),
        _pt(30, 10, 500, "c"),
        _pt(20, 11, 100, "a"),
        _pt(60, 5, 50, "b"),
    ]
    best = cheapest_point(pts, 50, 10)
    assert best is not None and best["method"] == "c"
    only_a = cheapest_point(pts, 50, 10, ["a"])
    assert only_a is not None and only_a["bytes_per_s"] == 900
    assert cheapest_point(pts, 10, 100) is None


# --- dead reckoning in the QoE pipeline ----------------------------------------------


def _screw_trace(duration: float = 3.0, rate: float = 90.0, w: float = 2.0) -> Trace:
    """One hand on a constant screw (twist from the origin pose), at the native rate."""
    t = np.arange(0.0, duration, 1.0 / rate)
    start = np.array([0.2, 1.0, -0.3, 1.0, 0.0, 0.0, 0.0])
    vel = np.array([0.8, 0.1, -0.4, 0.3, w, -0.5])
    poses = twist_extrapolate(start, vel, t)[:, None, :]
    return Trace("screw", t, poses, ("right",))


def _ideal(trace: Trace, rate: float, velocities: bool = False) -> KeyframeLog:
    send, idx = sample_keyframes(trace.times, rate)
    vel = keyframe_velocities(trace)[idx] if velocities else None
    return KeyframeLog(trace.times[idx], send, trace.poses[idx], vel)


def test_extrapolation_is_exact_on_a_constant_screw_and_counts_its_samples() -> None:
    """Screw dead reckoning continues a constant screw exactly; horizon 0 is the plain hold."""
    tr = _screw_trace()
    log = _ideal(tr, 10.0)
    d = 0.25 / 10.0 + 1.0 / 90.0
    plain = summarize([evaluate_group(tr, log, d, ["dq-slerp"])])
    hold = summarize(
        [evaluate_group(tr, log, d, ["dq-slerp"], extrapolate_horizon=0.0)], extrapolation=True
    )
    assert {k: hold["dq-slerp"]["hands"][k] for k in STAT_KEYS} == plain["dq-slerp"]["hands"]
    ext = summarize(
        [evaluate_group(tr, log, d, ["dq-slerp"], extrapolate_horizon=0.2)], extrapolation=True
    )
    h, e = hold["dq-slerp"]["hands"], ext["dq-slerp"]["hands"]
    assert set(h) == set(STAT_KEYS) | set(EXTRAPOLATION_KEYS)
    assert h["stall_fraction"] == e["stall_fraction"] > 0.5
    assert h["extrapolated_fraction"] == 0.0 and h["tip_p95_mm"] > 10.0
    # Every stall after the first two keyframes is dead-reckoned, and exactly so.
    assert 0.9 * e["stall_fraction"] < e["extrapolated_fraction"] <= e["stall_fraction"]
    assert e["tip_p95_mm"] < 1e-6 and e["correction_tip_p95_mm"] < 1e-6
    assert h["correction_tip_p95_mm"] > 10.0 and h["correction_events"] > 20


def test_velocity_extrapolation_needs_only_the_newest_keyframe() -> None:
    """Dead reckoning at the keyframe's own velocity follows a constant twist."""
    tr = _screw_trace()
    log = _ideal(tr, 10.0, velocities=True)
    # Exact velocities (float16 rounding aside): compare to the screw continued.
    d = 0.25 / 10.0 + 1.0 / 90.0
    out = summarize(
        [
            evaluate_group(
                tr, log, d, ["motor-hermite"], extrapolate_horizon=0.2, extrapolate_mode="auto"
            )
        ],
        extrapolation=True,
    )["motor-hermite"]["hands"]
    assert out["extrapolated_fraction"] == pytest.approx(out["stall_fraction"], abs=1e-12)
    assert out["tip_p95_mm"] < 0.5  # float16 velocities: sub-millimetre


def test_horizon_bounds_dead_reckoning_and_zero_means_hold() -> None:
    """Past the horizon the pose stops; horizon 0 renders exactly what holding renders."""
    tr = _screw_trace()
    log = _ideal(tr, 5.0)
    q = tr.times[(tr.times >= log.capture[0]) & (tr.times <= log.capture[-1])]
    play = playout_brackets(log.capture, log.arrival, q, 0.2 / 5.0 + 1.0 / 90.0)
    short = render_playout(log, q, play, "soa", extrapolate_horizon=0.02)
    assert short.beyond_horizon.sum() > 0
    assert np.all(short.extrapolated[short.beyond_horizon])
    zero = render_playout(log, q, play, "soa", extrapolate_horizon=0.0)
    plain = render_playout(log, q, play, "soa")
    np.testing.assert_array_equal(zero.poses, plain.poses)
    assert not zero.extrapolated.any() and zero.events.size > 0


def test_correction_blend_starts_at_the_old_pose_and_smooths_the_jump() -> None:
    """With a correction time the event frame shows the stale pose and the steps shrink."""
    tr = _screw_trace(w=6.0)
    # A wrong prediction: keyframes from a different, slower motion would be extreme;
    # holding (horizon 0) makes every event a visible jump instead.
    log = _ideal(tr, 10.0)
    q = tr.times[(tr.times >= log.capture[0]) & (tr.times <= log.capture[-1])]
    play = playout_brackets(log.capture, log.arrival, q, 0.25 / 10.0 + 1.0 / 90.0)
    jump = render_playout(log, q, play, "soa", extrapolate_horizon=0.0)
    smooth = render_playout(log, q, play, "soa", extrapolate_horizon=0.0, correction_time=0.03)
    ev = smooth.events
    assert ev.size > 10 and smooth.corrected[ev].all()
    # At the event frame the blend weight is 0: the previous (held) pose is still shown.
    np.testing.assert_allclose(smooth.poses[ev, 0, :3], smooth.poses[ev - 1, 0, :3], atol=1e-12)
    step_jump = np.linalg.norm(np.diff(jump.poses[:, 0, :3], axis=0), axis=1).max()
    step_smooth = np.linalg.norm(np.diff(smooth.poses[:, 0, :3], axis=0), axis=1).max()
    assert step_smooth < 0.75 * step_jump
    np.testing.assert_array_equal(smooth.jump_tip_mm, jump.jump_tip_mm)


def test_default_evaluation_is_unchanged_by_the_new_options() -> None:
    """Without a horizon evaluate_group's statistics keep exactly the old keys and values."""
    tr = _screw_trace()
    log = _ideal(tr, 12.0)
    d = 0.5 / 12.0 + 1.0 / 90.0
    a = summarize([evaluate_group(tr, log, d, ["soa", "motor-lerp"])])
    b = summarize([evaluate_group(tr, log, d, ["soa", "motor-lerp"], extrapolate_horizon=None)])
    assert a == b and set(a["soa"]["hands"]) == set(STAT_KEYS)


# --- a real run -------------------------------------------------------------------


@pytest.fixture(scope="module")
def small_run(dev_trace_path: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    trace = load_trace(dev_trace_path).window(30.0, 40.0)
    out = tmp_path_factory.mktemp("frontier")
    report = run_table1(
        [trace],
        rates=[10, 20],
        methods=["dq-slerp", "motor-cubic", "motor-hermite"],
        out_dir=out,
        bench=False,
        frontier_rates=[10, 20],
        frontier_fractions=(0.25, 1.0),
    )
    return {"report": report, "out": out, "trace": trace}


def test_small_real_run_writes_the_frontier(small_run: dict[str, object]) -> None:
    """A dev-trace window yields the 'frontier' key, its markdown section and its plot."""
    report = small_run["report"]
    out = small_run["out"]
    assert isinstance(report, dict) and isinstance(out, Path)
    fr = report["frontier"]
    nets = {"ideal", "excellent", "good", "mediocre", "poor"}
    assert set(fr["frontiers"]) == nets
    methods = {"soa", "dq-slerp", "motor-cubic", "motor-hermite"}
    assert {p["method"] for p in fr["points"]} == methods
    assert {p["variant"] for p in fr["points"]} == {"hold", "extrapolate", "smooth"}
    for net, front in fr["frontiers"].items():
        lat = [p["latency_ms"] for p in front]
        head = [p["headline_mm"] for p in front]
        assert lat == sorted(lat) and head == sorted(head, reverse=True), net
    hermite = [p for p in fr["points"] if p["method"] == "motor-hermite"]
    assert all(p["wire_bytes"] == 2460 for p in hermite)
    assert {"headline_target", "tiers"} <= set(fr["verdicts"])
    assert (out / "frontier.png").stat().st_size > 0
    assert "## Error versus latency" in (out / "table1.md").read_text()


@pytest.mark.parametrize("method", ["dq-slerp", "motor-cubic", "motor-hermite"])
@pytest.mark.parametrize("variant", ["hold", "extrapolate", "smooth"])
def test_frontier_points_equal_evaluate_group(
    small_run: dict[str, object], method: str, variant: str
) -> None:
    """Each ideal-network point is what evaluate_group gives with the same D and options."""
    report = small_run["report"]
    trace = small_run["trace"]
    assert isinstance(report, dict) and isinstance(trace, Trace)
    cfg = report["frontier"]["config"]
    hands = trace.select(["left", "right"])
    vel = keyframe_velocities(trace)[:, 1:]
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
            correction_time=cfg["correction_time_s"] if variant == "smooth" else 0.0,
            extrapolate_mode="auto",
        )
        st = summarize([g], extrapolation=True)[method]["hands"]
        # (the report rounds to 6 decimals)
        assert p["headline_mm"] == pytest.approx(st["tip_p95_mm"], rel=1e-9, abs=1e-5)
        assert p["stall_fraction"] == pytest.approx(st["stall_fraction"], abs=1e-5)
        assert p["latency_ms"] == pytest.approx(1000 * d, abs=1e-5)


def test_refinement_bisects_to_the_cheapest_qualifying_rate() -> None:
    """With quality rising with rate, bisection finds the exact lowest qualifying rate."""
    from posecast.scenarios.table1 import _refine

    def point(net: str, m: str, r: int) -> dict[str, object]:
        # SoA: 100 mm at 20 Hz; "x" reaches 100 mm from 13 Hz on, at the same latency.
        head = 2000.0 / r if m == "soa" else (90.0 if r >= 13 else 200.0)
        return {
            "network": net,
            "method": m,
            "rate": r,
            "fraction": 1.0,
            "variant": "hold",
            "latency_ms": 50.0,
            "headline_mm": head,
            "bytes_per_s": 100.0 * r,
        }

    grid = [5, 10, 20, 30]
    points = [point("ideal", m, r) for m in ("soa", "x") for r in grid]
    calls: list[tuple[str, list[int]]] = []

    def evaluate(net: str, maker: object, m: str, rates: list[int]) -> list[dict[str, object]]:
        calls.append((m, rates))
        return [point(net, m, r) for r in rates]

    added = _refine(points, ["soa", "x"], {"t": 20}, [("ideal", _ideal_log, grid)], 5, evaluate)
    assert 13 in added["ideal"]["x"] and len(calls) <= 4
    best = cheapest_point(points, 50.0, 100.0, ["x"])
    assert best is not None and best["rate"] == 13
