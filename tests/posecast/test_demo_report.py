"""What the demo prints after its tables: the verdict from given numbers, the next
steps, and tables that fit 80 columns."""

from __future__ import annotations

import io

import pytest
from rich.console import Console

from posecast.cli import common, report
from posecast.cli.report import demo_next_steps, motion_note, verdict


def _methods(**hands_p95: float) -> dict[str, dict[str, dict[str, float]]]:
    return {
        m: {"hands": {"tip_p95_mm": v}, "head": {"tip_p95_mm": 1.0}} for m, v in hands_p95.items()
    }


def test_a_method_beating_soa_is_named_with_the_margin() -> None:
    """The best method is set against soa (what engines do), in mm of hands p95 tip error."""
    line = verdict(
        _methods(soa=220.4, **{"dq-slerp": 201.2, "motor-lerp": 190.0}), 15, "traces:sample"
    )
    assert line == (
        "verdict: at 15 Hz on this motion (Beat Saber, a worst case for hands), motor-lerp "
        "beats soa by 30.4 mm p95 on the hands (190.0 vs 220.4 mm tip error); "
        "see docs/concepts/qoe.md"
    )


def test_soa_winning_is_said_against_the_runner_up() -> None:
    """When soa is best, the verdict says so against the next best method."""
    line = verdict(
        _methods(soa=220.4, **{"dq-slerp": 227.7, "motor-lerp": 226.1}), 15, "traces:sample"
    )
    assert "soa beats motor-lerp by 5.7 mm p95 on the hands (220.4 vs 226.1 mm" in line


def test_within_two_percent_is_a_tie() -> None:
    """226.1 vs 227.7 mm (0.7 %) is a tie, not a win."""
    line = verdict(_methods(**{"dq-slerp": 227.7, "motor-lerp": 226.1}), 30, "synthetic")
    assert "at 30 Hz on this motion (synthetic motion, calmer than a game)" in line
    assert "motor-lerp and dq-slerp tie on the hands: 226.1 vs 227.7 mm" in line
    assert "within 2 %" in line


def test_a_starved_run_says_rerun_and_a_lone_bot_has_no_verdict() -> None:
    """Starved: the verdict asks for an idle machine; no hands (a lone bot): no winner."""
    line = verdict(_methods(soa=10.0, **{"motor-lerp": 5.0}), 15, "x/y/trace.csv", starved=True)
    assert "(the trace trace.csv)" in line and "rerun on an idle one" in line
    assert verdict({"soa": {}}, 15, "traces:sample").startswith("verdict: none at 15 Hz")
    assert "a lone bot sees nobody" in verdict({"soa": {}}, 15, "synthetic", lone=True)
    nan = float("nan")
    assert "verdict: none" in verdict(_methods(soa=nan), 15, "traces:sample")


def test_one_method_is_described_alone() -> None:
    line = verdict(_methods(soa=12.34), 20, "throw-catch")
    assert line.startswith("verdict: at 20 Hz on this motion (the throw-catch scene), soa shows")
    assert "12.3 mm off (p95 tip)" in line


@pytest.mark.parametrize("motion", ["traces:sample", "traces:eval", "synthetic:orbit"])
def test_next_steps_are_commands(motion: str) -> None:
    """Each step is a posecast command line and says what it shows."""
    lines = demo_next_steps("recordings/demo.mcap", motion)
    assert lines[0] == "next:"
    assert all(line.startswith("  posecast ") and "  # " in line for line in lines[1:])
    assert any("replay --offline recordings/demo.mcap" in line for line in lines)
    assert all(len(line) <= 80 for line in lines), lines
    assert motion_note(motion)


def _swarm(method: str, cls: str) -> dict[str, object]:
    st = {
        "pos_p50_mm": 33.6, "pos_p95_mm": 1475.8, "rot_p50_deg": 7.32, "rot_p95_deg": 134.33,
        "tip_p50_mm": 49.1, "tip_p95_mm": 1805.6, "stall_fraction": 1.0,
        "vel_p50_mps": 1.0, "vel_p95_mps": 2.0,
    }  # fmt: skip
    bot = {"id": 12, "name": "bot12", "rate_hz": 13.4, "delay_ms": 1183.7,
           "render_cpu_ms_per_frame": 10.41, "clock_rtt_ms": 107.37,
           "snapshot_age_ms_p50": 138.55, "role": None, "object": {}}  # fmt: skip
    return {
        "methods": {m: {"hands": st, cls: st} for m in ("soa", "dq-slerp", method)},
        "bots": [bot],
        "wire": {"bytes_per_pose": 9.7, "bytes_per_s": 1800.0},
    }


@pytest.mark.parametrize(("method", "cls"), [("motor-lerp", "head"), ("motor-hermite", "head")])
def test_the_tables_fit_80_columns(monkeypatch: pytest.MonkeyPatch, method: str, cls: str) -> None:
    """At 80 columns no table line is wider and no name is cut ("dq-sl…")."""
    out = io.StringIO()
    narrow = Console(file=out, width=80, force_terminal=False)
    monkeypatch.setattr(common, "console", narrow)
    monkeypatch.setattr(report, "console", narrow)
    report.print_swarm(
        _swarm(method, cls), "posecast demo: 6 bots at 15 Hz for 20 s (traces:sample)"
    )
    text = out.getvalue()
    assert "…" not in text, text
    assert max(len(line) for line in text.splitlines()) <= 80, text
    assert method in text and "dq-slerp" in text and "1805.6" in text and "bot12" in text


def test_the_verdict_points_to_a_page_that_exists() -> None:
    """The page the verdict names is in the repository (a moved page fails here)."""
    from pathlib import Path

    assert (Path(__file__).resolve().parents[2] / report.DEMO_DOC).is_file()
