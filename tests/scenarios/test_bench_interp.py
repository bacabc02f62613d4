"""``posecast bench interp``'s parts: the render-frame room, the report, the plain child.

The bench never passes or fails on a time; these tests check what it measures
on (100 streams of real motion, rendered), that the report carries the frame
and entry-path figures, and that the plain-interpreter child reports every
method. No wall-clock figure is asserted.
"""

from __future__ import annotations

import io

import numpy as np
import pytest
from rich.console import Console

import posecast.scenarios.bench_interp as bench
from posecast.client.render import render_buffers


def test_frame_room_holds_100_streams_of_real_motion() -> None:
    """Every stream has its keyframes; the playout times render them with few stalls."""
    room, playout = bench.frame_room()
    assert len(room) == bench.FRAME_STREAMS
    counts = room.counts[: len(room)]
    assert counts.min() >= 50  # 4 s at 15 Hz, a duplicate or two dropped at most
    stalls = 0
    for t in playout[::30]:
        frame = render_buffers(room, float(t), ["soa", "dq-slerp", "motor-lerp"])
        stalls += int(frame.stalled.sum())
        for poses in frame.poses.values():
            assert poses.shape == (bench.FRAME_STREAMS, 7) and np.all(np.isfinite(poses))
            np.testing.assert_allclose(np.linalg.norm(poses[:, 3:], axis=1), 1.0, atol=1e-6)
    assert stalls < len(playout[::30])  # the times lie inside the streams' keyframes
    # Real motion: the streams move, and not all the same way.
    assert np.ptp(room.poses[0, :, 0]) > 0.01


def test_report_carries_frame_figures_and_targets(monkeypatch: pytest.MonkeyPatch) -> None:
    """A short run (batch 1, few repeats) reports and prints the frame for each method set."""
    monkeypatch.setattr(bench, "TRACK_RUNS", 20)
    monkeypatch.setattr(bench, "_REPEATS", 2)
    monkeypatch.setattr(bench, "_MAX_CASE_S", 0.05)
    out = io.StringIO()
    report = bench.run_interp_bench((1,), Console(file=out, width=200), entry_paths=False)
    keys = [" + ".join(m) for m in bench.FRAME_SETS]
    assert list(report["frame"]) == keys
    for key in keys:
        fig = report["frame"][key]
        assert 0 < fig["best_us"] <= fig["median_us"] <= fig["p90_us"]
        assert fig["numpy_calls"] > 1
        assert report["targets"][f"frame {key}"]["target"] in (50.0, 100.0)
    for name in bench.METHODS:
        assert report["frame"][name]["kernel_us"] > 0
    assert report["entry_paths"] == {}
    text = out.getvalue()
    assert "Render frame" in text and "frame soa + dq-slerp + motor-lerp" in text


def test_plain_python_child_reports_every_method() -> None:
    """``python -m posecast.scenarios.bench_interp --batch N``: a fresh interpreter, JSON out."""
    rates = bench._plain_python_rates(64)
    assert isinstance(rates, dict), rates
    assert set(rates) == set(bench.ALL_METHODS)
    assert all(np.isfinite(v) and v > 0 for v in rates.values())


def test_import_interp_child_reports_the_pair_methods() -> None:
    """``python -c`` importing ``interp`` only (the notebook path) times the pair methods."""
    rates = bench._plain_python_rates(64, notebook=True)
    assert isinstance(rates, dict), rates
    assert set(rates) == set(bench.METHODS)
    assert all(np.isfinite(v) and v > 0 for v in rates.values())


def test_entry_table_puts_each_path_beside_the_first() -> None:
    """Three entry paths print side by side with two ratios; a failed child shows why."""
    report = {
        "entry_paths": {
            "cli": {m: 2.0e6 for m in bench.ALL_METHODS},
            "plain": {m: 1.0e6 for m in bench.ALL_METHODS},
            "notebook": "failed: boom",
        }
    }
    out = io.StringIO()
    Console(file=out, width=250).print(bench._entry_table(report))
    text = out.getvalue()
    assert "path 2 / path 1" in text and "path 3 / path 1" in text
    assert "0.50" in text and "failed: boom" in text
