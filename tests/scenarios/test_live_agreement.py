"""Live vs offline Table 1: the offline counterpart and the tolerance, without sockets."""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from posecast.scenarios.live_agreement import (
    SenderView,
    Tolerance,
    check_agreement,
    live_markdown,
    model_rate,
    simulate_receiver,
    write_live,
)
from posecast.scenarios.network import Tier, affordable_rate
from posecast.scenarios.traces import Trace


def _stats(p50: float, p95: float, stall: float = 0.0) -> dict[str, float]:
    return {
        "pos_p50_mm": p50 / 2,
        "pos_p95_mm": p95 / 2,
        "rot_p50_deg": 1.0,
        "rot_p95_deg": 5.0,
        "tip_p50_mm": p50,
        "tip_p95_mm": p95,
        "stall_fraction": stall,
    }


def _side(hands_p95: float, stall: float, **extra: float) -> dict[str, Any]:
    methods = {
        m: {"hands": _stats(20.0, hands_p95, stall), "head": _stats(1.0, 4.0, stall)}
        for m in ("soa", "dq-slerp")
    }
    out: dict[str, Any] = {
        "methods": methods,
        "methods_ample": copy.deepcopy(methods),
        "rate_hz": 20.0,
        "server_rate_hz": 20.0,
        "bytes_per_s": 10_000.0,
        "delay_ms": 100.0,
        "lost_fraction": 0.01,
        "offered": 2000.0,
    }
    out.update(extra)
    return out


def _failed(result: dict[str, Any]) -> list[str]:
    return [c["what"] for c in result["checks"] if not c["ok"]]


def test_figures_inside_the_tolerance_agree() -> None:
    """Differences just inside every limit pass, and every compared figure is listed."""
    tol = Tolerance()
    offline = _side(100.0, 0.01, tier_loss=0.01)
    live = _side(
        100.0 * (1 + tol.error_rel) - 0.1,
        0.01 + tol.stall_abs_pp / 100 - 0.001,
        rate_hz=20.0 * (1 - tol.rate_rel) + 0.01,
        bytes_per_s=10_000.0 * (1 + tol.bytes_rel) - 1,
        delay_ms=100.0 + tol.delay_abs_ms - 0.1,
        loop_lag_p95_ms=5.0,
    )
    res = check_agreement(live, offline, tol)
    assert res["pass"], _failed(res)
    names = {c["what"] for c in res["checks"]}
    assert "soa hands tip_p95_mm (ample D)" in names
    assert "dq-slerp head tip_p50_mm (live D)" in names
    assert {"stall % at the live D", "lost snapshots %", "playout delay D"} <= names


def test_a_headline_outside_the_tolerance_fails() -> None:
    """One method's hands p95 at the ample D 20 % off (limit 15 %) fails, and only that."""
    offline = _side(100.0, 0.0, tier_loss=0.01)
    live = _side(100.0, 0.0)
    live["methods_ample"]["dq-slerp"]["hands"]["tip_p95_mm"] = 120.0
    res = check_agreement(live, offline, Tolerance())
    assert not res["pass"]
    assert _failed(res) == ["dq-slerp hands tip_p95_mm (ample D)"]
    bad = next(c for c in res["checks"] if not c["ok"])
    assert bad["diff"] == pytest.approx(20.0) and bad["limit"] == pytest.approx(15.0)


def test_small_errors_use_the_absolute_floor() -> None:
    """A 0.8 mm difference on a 2 mm head error is 40 % but inside the 1 mm floor."""
    offline = _side(100.0, 0.0, tier_loss=0.0, lost_fraction=0.0)
    live = _side(100.0, 0.0, lost_fraction=0.0)
    live["methods"]["soa"]["head"]["tip_p50_mm"] = 1.8
    assert check_agreement(live, offline, Tolerance())["pass"]
    live["methods"]["soa"]["head"]["tip_p50_mm"] = 2.1
    assert _failed(check_agreement(live, offline, Tolerance())) == ["soa head tip_p50_mm (live D)"]


def test_stalls_delay_rate_lag_and_loss_each_fail_on_their_own() -> None:
    """Each timing figure outside its limit is named; a missing figure fails too."""
    tol = Tolerance()
    offline = _side(100.0, 0.0, tier_loss=0.01)
    cases = {
        "stall % at the live D": {"methods": _side(100.0, 0.05)["methods"]},
        "playout delay D": {"delay_ms": 100.0 + tol.delay_abs_ms + 1},
        "keyframes/s per stream": {"rate_hz": 18.0},
        "server rate": {"server_rate_hz": 15.0},
        "link bytes/s per subscriber": {"bytes_per_s": 12_000.0},
        "event-loop lag p95 (live only)": {"loop_lag_p95_ms": tol.loop_lag_p95_ms + 5},
        # 1 % expected over 2000 + 2000 snapshots: sigma 0.31 points, limit 0.94.
        "lost snapshots %": {"lost_fraction": 0.025},
    }
    for name, change in cases.items():
        res = check_agreement({**_side(100.0, 0.0), **change}, offline, tol)
        assert _failed(res) == [name], (name, _failed(res))
    live = _side(100.0, 0.0)
    del live["bytes_per_s"]
    assert _failed(check_agreement(live, offline, tol)) == ["link bytes/s per subscriber"]
    live = _side(100.0, 0.0)
    live["methods_ample"]["soa"]["hands"]["tip_p95_mm"] = math.nan
    assert _failed(check_agreement(live, offline, tol)) == ["soa hands tip_p95_mm (ample D)"]


def _trace(rate: float = 90.0, seconds: float = 6.0, t0: float = 100.0) -> Trace:
    """A hand circling at 1 turn/s (and a still head), sampled at ``rate``, from t0."""
    t = np.arange(0.0, seconds, 1.0 / rate)
    poses = np.zeros((t.size, 3, 7))
    poses[:, :, 3] = 1.0
    poses[:, 0, 1] = 1.6
    for j in (1, 2):
        poses[:, j, 0] = 0.3 * np.cos(2 * np.pi * t)
        poses[:, j, 1] = 1.2 + 0.3 * np.sin(2 * np.pi * t)
    return Trace("circle", t + t0, poses, ("head", "left", "right"))


def test_published_is_the_newest_sample_at_the_last_poll() -> None:
    """A sender polling at 30 Hz from t0 has published the newest sample <= its last poll."""
    tr = _trace(90.0, 2.0, t0=10.0)
    sv = SenderView(tr, {"left": (10.0, 12.0)}, t0=10.0, send_rate=30.0, end=11.0)
    idx = sv.published(np.array([9.9, 10.0, 10.05, 10.5, 10.99, 11.5]))
    # last polls: none, 10.0, 10.0333, 10.5, 10.9667, then 11.0 (the last before end)
    want = [-1, 0, 3, 45, 87, 90]
    assert idx.tolist() == want


def test_a_late_poll_publishes_a_newer_sample_later() -> None:
    """With 12 ms of timer lag the poll due at 10.002 runs at 10.014 and takes a newer sample."""
    tr = _trace(90.0, 1.0, t0=10.0)  # samples at 10 + j/90
    sv = SenderView(tr, {"left": (10.0, 11.0)}, t0=10.002, send_rate=30.0)
    times = np.array([10.005, 10.02, 10.04, 10.05])
    # polls at 10.002, 10.0353: samples 0, 0, 3, 3
    assert sv.published(times).tolist() == [0, 0, 3, 3]
    late = sv.published(times, np.array([0.012]), np.random.default_rng(0))
    # polls at 10.014, 10.0473: nothing yet at 10.005; then samples 1, 1 and 4.
    assert late.tolist() == [-1, 1, 1, 4]


def test_offline_counterpart_on_a_fixed_delay_link() -> None:
    """No jitter, no loss: every tick delivered after the latency; D rule and bytes follow."""
    tier = Tier("fixed", 20.0, 1000.0, latency_ms=30.0, jitter_ms=0.0, loss_pct=0.0)
    tr = _trace()
    window = (101.0, 105.0)
    sv = SenderView(tr, {"left": window, "head": window}, t0=100.0, send_rate=90.0)
    sim = simulate_receiver(
        [sv], tier=tier, rate=20.0, phase=0.25, frame_bytes=300, methods=["soa"], delay=0.2
    )
    assert sim.lost == 0 and sim.skipped == 0 and sim.delivered == sim.frames
    assert sim.rate_hz == pytest.approx(20.0, rel=1e-3)
    assert sim.bytes_per_s == pytest.approx(20.0 * 300, rel=0.02)
    # Age = latency + (tick - newest 90 Hz sample): at most one native frame.
    assert 1 / 20 + 0.030 <= sim.rule_delay_s <= 1 / 20 + 0.030 + 1 / 90 + 1e-9
    hands = sim.equal_d["soa"]["hands"]
    assert hands.stalls == 0 and hands.samples > 0
    # With D = 0.2 s everything is bracketed: errors at the live D equal the ample D's.
    assert hands.stats() == sim.ample_d["soa"]["hands"].stats()
    assert set(sim.rule_d["soa"]) == {"hands", "head"}


def test_offline_counterpart_loses_whole_snapshots() -> None:
    """A lossy tier loses about its share of snapshots, for every sender at once."""
    tier = Tier("lossy", 30.0, 1000.0, latency_ms=20.0, jitter_ms=5.0, loss_pct=10.0)
    a, b = _trace(t0=0.0, seconds=30.0), _trace(t0=0.0, seconds=30.0)
    win = (1.0, 29.0)
    senders = [SenderView(x, {"left": win}, t0=0.0, send_rate=90.0) for x in (a, b)]
    sim = simulate_receiver(
        senders, tier=tier, rate=30.0, phase=0.0, frame_bytes=300, methods=["soa"], delay=0.1
    )
    share = sim.lost / sim.frames
    assert 0.07 < share < 0.13
    assert sim.rate_hz == pytest.approx(30.0 * (1 - share), rel=0.03)
    # Same seed, same realisation; another seed, another one.
    again = simulate_receiver(
        senders, tier=tier, rate=30.0, phase=0.0, frame_bytes=300, methods=["soa"], delay=0.1
    )
    other = simulate_receiver(
        senders,
        tier=tier,
        rate=30.0,
        phase=0.0,
        frame_bytes=300,
        methods=["soa"],
        delay=0.1,
        seed=1,
    )
    assert again.lost == sim.lost and other.lost != sim.lost


def test_model_rate_is_capped_by_the_bandwidth() -> None:
    """The server's rate as the model predicts it: asked, tier max, or the cap."""
    tier = Tier("thin", 30.0, 80.0, 10.0, 1.0, 0.0)  # 10 000 B/s
    assert model_rate(tier, 30.0, 1000) == pytest.approx(10.0)
    assert model_rate(tier, 5.0, 1000) == 5.0
    assert model_rate(tier, 30.0, 100) == pytest.approx(affordable_rate(tier, 100)) == 30.0


def _live_report(ok: bool) -> dict[str, Any]:
    offline = _side(100.0, 0.0, tier_loss=0.01)
    offline["methods_rule_d"] = offline["methods"]
    live = _side(100.0 if ok else 150.0, 0.0, loop_lag_p95_ms=3.0)
    return {
        "config": {
            "bots": 2,
            "duration_s": 5.0,
            "send_rate_hz": 90.0,
            "render_rate_hz": 10.0,
            "motions": ["a.csv", "b.csv"],
            "tolerance": Tolerance().as_dict(),
        },
        "tiers": [
            {
                "tier": "good",
                "live": live,
                "offline": offline,
                "agreement": check_agreement(live, offline, Tolerance()),
            }
        ],
        "pass": ok,
    }


def test_markdown_shows_the_verdict_and_the_failed_checks() -> None:
    """The section names the tolerance, marks a failing tier and lists what failed."""
    good = "\n".join(live_markdown(_live_report(True)))
    assert "## Live vs offline" in good and "**pass**" in good and "15 %" in good
    bad = "\n".join(live_markdown(_live_report(False)))
    assert "**FAIL**" in bad and "soa hands tip_p95_mm (ample D)" in bad
    assert "does not agree" in bad


def test_write_live_adds_the_key_and_the_section(tmp_path: Path) -> None:
    """table1.json gains "live" (other keys kept); table1.md gains the section before plots."""
    (tmp_path / "table1.json").write_text(json.dumps({"tiers": [1, 2], "curves": {}}))
    (tmp_path / "table1.md").write_text("# Table 1\n\nbody\n\n## Plots\n\n![p](p.png)\n")
    report = _live_report(True)
    report["tiers"][0]["live"]["delay_ms"] = math.nan
    write_live(tmp_path, report)
    data = json.loads((tmp_path / "table1.json").read_text())
    assert data["tiers"] == [1, 2] and data["live"]["pass"] is True
    assert data["live"]["tiers"][0]["live"]["delay_ms"] is None
    md = (tmp_path / "table1.md").read_text()
    assert md.index("## Live vs offline") < md.index("## Plots") and "body" in md


def test_markdown_puts_auto_rates_beside_the_fixed_rate() -> None:
    """A tier with an ``auto`` run gains the fixed-vs-auto table: both policies, the
    server's mean rate (lowest-highest), the stall share and the tip error."""
    report = _live_report(True)
    tier = report["tiers"][0]
    tier["asked_rate_hz"] = 20.0
    tier["auto"] = _side(80.0, 0.002, server_rate_mean_hz=26.5, server_rate_low_hz=21.0,
                         server_rate_high_hz=30.0)  # fmt: skip
    md = "\n".join(live_markdown(report))
    assert "### Auto rates beside the tier's rate (`--live-auto`)" in md
    assert "| good | fixed 20.0 Hz | 20.0 (-" in md
    assert "| good | auto | 26.5 (21.0-30.0) | 20.00 | 10000 | 100.0 | 0.20 % | 20.0 / 80.0 |" in md
    assert "auto" not in "\n".join(live_markdown(_live_report(True)))
