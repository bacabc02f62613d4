"""Decimation analysis (the paper's Tables 2 and 3): Euler angles, the metric, sources."""

from __future__ import annotations

import itertools
import math
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from posecast.recorder.analyze import (
    analyze,
    decimate,
    format_analysis,
    quat_to_euler,
    relative_error_pct,
)
from posecast.recorder.replay import synthesize_recording
from posecast.scenarios.traces import SAMPLE_DIR, Trace, load_trace

SEQUENCES = [
    "".join(a) for a in itertools.product("xyz", repeat=3) if a[0] != a[1] and a[1] != a[2]
]


def _wxyz(q_xyzw: np.ndarray) -> np.ndarray:
    return q_xyzw[..., [3, 0, 1, 2]]


@pytest.mark.parametrize("seq", [*SEQUENCES, *(s.upper() for s in SEQUENCES)])
def test_euler_angles_match_scipy(seq: str) -> None:
    """quat_to_euler (w first) equals scipy's as_euler for every sequence."""
    rot = Rotation.random(500, random_state=7)
    ours = quat_to_euler(_wxyz(rot.as_quat()), seq)
    ref = rot.as_euler(seq, degrees=True)
    diff = (ours - ref + 180.0) % 360.0 - 180.0  # the +-180 seam is one angle
    assert np.abs(diff).max() < 1e-9


@pytest.mark.parametrize("seq", ["XYZ", "xyz", "ZXZ", "yxy"])
def test_euler_angles_at_gimbal_lock_describe_the_rotation(seq: str) -> None:
    """At gimbal lock the angles still compose back to the same rotation."""
    middles = (0.0, 180.0) if seq[0].lower() == seq[2].lower() else (90.0, -90.0)
    for mid in middles:
        rot = Rotation.from_euler(seq, [35.0, mid, -20.0], degrees=True)
        ours = quat_to_euler(_wxyz(rot.as_quat()), seq)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # scipy warns about the lock it resolves too
            back = Rotation.from_euler(seq, ours, degrees=True)
        assert np.degrees((back * rot.inv()).magnitude()) < 1e-9


def test_euler_rejects_bad_sequences() -> None:
    """Mixed case, repeated consecutive axes and unknown axes are refused."""
    q = np.array([1.0, 0.0, 0.0, 0.0])
    for bad in ("XyZ", "XXY", "abc", "XY"):
        with pytest.raises(ValueError):
            quat_to_euler(q, bad)


def test_decimate_keeps_every_kth_and_gives_exact_fractions() -> None:
    """Keep 0, k, 2k...; dropped frames between kept ones get a = j/k; no tail frames."""
    dropped, lo, a = decimate(10, 2)
    assert dropped.tolist() == [1, 3, 5, 7]
    assert lo.tolist() == [0, 2, 4, 6]
    assert a.tolist() == [0.5] * 4
    dropped, lo, a = decimate(10, 3)
    assert dropped.tolist() == [1, 2, 4, 5, 7, 8]
    assert lo.tolist() == [0, 0, 3, 3, 6, 6]
    np.testing.assert_allclose(a, [1 / 3, 2 / 3] * 3)
    dropped, _lo, _a = decimate(8, 3)  # frames 7 is after the last kept frame (6)
    assert dropped.tolist() == [1, 2, 4, 5]


def test_relative_error_is_nan_for_a_zero_true_vector() -> None:
    """|r - t| / |t| * 100, NaN where |t| is 0."""
    out = relative_error_pct([[1.0, 0.0, 0.0], [3.0, 4.0, 0.0]], [[0.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    assert math.isnan(out[0])
    assert out[1] == pytest.approx(400.0 / 3.0)


def _parabola_trace() -> Trace:
    """Head moving along x = t^2 with a constant 30 deg rotation about x."""
    n = 5
    poses = np.zeros((n, 1, 7))
    poses[:, 0, 0] = np.arange(n, dtype=float) ** 2
    poses[:, 0, 1] = 1.0
    half = np.radians(30.0) / 2
    poses[:, 0, 3:] = [math.cos(half), math.sin(half), 0.0, 0.0]
    return Trace("parabola", np.arange(n) / 10.0, poses, ("head",))


def test_paper_metric_by_hand() -> None:
    """Midpoints of x = t^2 are off by 1: relative errors 1/sqrt(2) and 1/sqrt(82)."""
    result = analyze(_parabola_trace(), keep_every=(2,), methods=("soa", "dq-slerp", "motor-lerp"))
    expected = 100.0 * (1 / math.sqrt(2) + 1 / math.sqrt(82)) / 2
    for m in ("soa", "dq-slerp", "motor-lerp"):
        st = result["tables"]["2"]["methods"][m]["classes"]["head"]
        assert st["frames"] == 2
        assert st["translation_rel_pct"] == pytest.approx(expected, rel=1e-9)
        assert st["euler_rel_pct"] == pytest.approx(0.0, abs=1e-9)
        assert st["pos_p50_mm"] == pytest.approx(1000.0)  # the 1 m miss, in mm


def test_analyze_an_eval_like_dev_trace(dev_trace_path: Path) -> None:
    """A real trace: classes, frame counts, and ScLERP = motor LERP at a = 1/2."""
    trace = load_trace(dev_trace_path).window(0.0, 20.0)
    methods = ("soa", "dq-slerp", "motor-lerp", "motor-cubic", "motor-hermite")
    result = analyze(trace, keep_every=(2, 3), methods=methods)
    n = trace.times.size
    for k in (2, 3):
        dropped = decimate(n, k)[0].size
        table = result["tables"][str(k)]
        assert table["fractions"] == [j / k for j in range(1, k)]
        for m in methods:
            classes = table["methods"][m]["classes"]
            assert list(classes) == ["hands", "head", "all"]
            assert classes["head"]["frames"] == dropped
            assert classes["hands"]["frames"] == 2 * dropped
            assert classes["all"]["frames"] == 3 * dropped
            for key in ("translation_rel_pct", "euler_rel_pct", "tip_p95_mm"):
                assert math.isfinite(classes["all"][key]) and classes["all"][key] >= 0
            # wrapping the angle differences can only shrink the error
            assert classes["all"]["euler_rel_wrapped_pct"] <= classes["all"]["euler_rel_pct"]
    half = result["tables"]["2"]["methods"]
    a, b = half["dq-slerp"]["classes"]["all"], half["motor-lerp"]["classes"]["all"]
    for key in ("translation_rel_pct", "euler_rel_pct", "pos_p95_mm", "tip_p95_mm"):
        assert a[key] == pytest.approx(b[key], rel=1e-6)
    assert result["paper"]["available"] is False
    text = format_analysis(result)
    assert "Keep 1 in 2" in text and "Keep 1 in 3" in text and "n/a" in text


def test_analyze_pools_several_sources(dev_trace_path: Path) -> None:
    """Two sources pool their frames; each keeps its own breakdown."""
    a = load_trace(dev_trace_path).window(0.0, 5.0)
    b = Trace("second", a.times, a.poses[:, :, :].copy(), a.streams)
    result = analyze([a, b], keep_every=(2,), methods=("soa",))
    alone = analyze(a, keep_every=(2,), methods=("soa",))
    both = result["tables"]["2"]["methods"]["soa"]["classes"]["all"]
    one = alone["tables"]["2"]["methods"]["soa"]["classes"]["all"]
    assert both["frames"] == 2 * one["frames"]
    assert both["translation_rel_pct"] == pytest.approx(one["translation_rel_pct"])
    assert set(result["per_source"]) == {a.name, "second"}


def test_analyze_a_recording_skips_velocity_methods(tmp_path: Path) -> None:
    """A recording's streams are its keyframes; velocity methods are skipped with a note."""
    # A 90 Hz trace: every 30 Hz send time finds a fresh native sample.
    quest2 = SAMPLE_DIR / "S03_quest2_expert_FS.csv.gz"
    path = synthesize_recording(tmp_path, users=2, rate=30.0, duration=4.0, traces=str(quest2))
    result = analyze(path, keep_every=(2, 3), methods=("soa", "motor-lerp", "motor-hermite"))
    (src,) = result["sources"]
    assert src["kind"] == "recording" and src["streams"] == 6
    assert src["rate_hz"] == pytest.approx(30.0, rel=0.05)
    table = result["tables"]["3"]["methods"]
    assert table["motor-hermite"] == {"skipped": "no source with velocities"}
    assert any("motor-hermite: skipped" in n for n in result["notes"])
    assert set(table["soa"]["classes"]) == {"hands", "head", "all"}
    assert "skipped" in format_analysis(result)


def test_analyze_a_recording_with_velocities_and_a_wide_window(tmp_path: Path) -> None:
    """Recorded velocities drive motor-hermite; motor-quintic gets 2 kept neighbours a side."""
    path = synthesize_recording(tmp_path, users=2, rate=30.0, duration=4.0, velocities=True)
    methods = ("soa", "motor-cubic", "motor-quintic", "motor-hermite")
    result = analyze(path, keep_every=(2, 3), methods=methods)
    assert not any("skipped" in n for n in result["notes"])
    for k in ("2", "3"):
        table = result["tables"][k]["methods"]
        for m in methods:
            hands = table[m]["classes"]["hands"]
            assert hands["frames"] > 0 and 0 < hands["translation_rel_pct"] < 100, (k, m)
        # the wider window sees more of the motion than the 4-keyframe one: it differs
        assert (
            table["motor-quintic"]["classes"]["hands"]["pos_p95_mm"]
            != table["motor-cubic"]["classes"]["hands"]["pos_p95_mm"]
        )


def test_analyze_refuses_unknown_methods_and_keep_one(dev_trace_path: Path) -> None:
    """An unknown interpolator or keep_every < 2 is refused."""
    with pytest.raises(KeyError):
        analyze(dev_trace_path, methods=("nope",))
    with pytest.raises(ValueError):
        analyze(dev_trace_path, keep_every=(1,))
