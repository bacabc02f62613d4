"""Offline replay of a recording: rendered files, QoE by the one definition, the bench."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from posecast.interp import info as interp_info
from posecast.recorder import info as recording_info
from posecast.recorder.export import read_session
from posecast.recorder.replay import (
    bench_replay,
    recording_stem,
    replay_offline,
    synthesize_recording,
)
from posecast.scenarios.motion import MotionSpec
from posecast.scenarios.qoe import (
    KeyframeLog,
    evaluate_group,
    ideal_delay,
    sample_keyframes,
    summarize,
)
from posecast.scenarios.traces import Trace


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three users x 3 streams x 30 Hz x 5 s from the dev traces."""
    return synthesize_recording(tmp_path_factory.mktemp("rec"), users=3, duration=5.0, seed=4)


def test_synthesised_recording_holds_the_traces(recording: Path) -> None:
    """Users, 30 Hz streams, and poses equal to the traces' samples at the capture times."""
    summary = recording_info(recording)
    assert summary["complete"] and summary["drops"]["total"] == 0
    assert len(summary["users"]) == 3 and len(summary["streams"]) == 9
    for s in summary["streams"]:
        assert s["rate"] == pytest.approx(30.0, rel=0.1)
    data = read_session(recording)
    for s in data.streams:
        user = data.users[s.user]
        assert user.label is not None
        truth = MotionSpec.parse(user.label).truth()
        j = truth.streams.index(s.name)
        idx = np.searchsorted(truth.times, s.times)
        np.testing.assert_allclose(truth.times[idx], s.times, rtol=0, atol=1e-9)
        assert np.array_equal(truth.poses[idx, j].astype(np.float32), s.poses)
        assert np.all(s.arrival > s.times)


def test_replay_writes_csv_and_npz_per_method(recording: Path, tmp_path: Path) -> None:
    """Every stream rendered at 90 Hz from its first to last keyframe; CSV = NPZ."""
    result = replay_offline(recording, ["soa", "motor-cubic"], 10.0, tmp_path, 90.0)
    data = read_session(recording)
    stem = recording_stem(recording)
    assert set(result["files"]) == {"soa", "motor-cubic"}
    for m in ("soa", "motor-cubic"):
        files = result["files"][m]
        assert Path(files["csv"]).name == f"{stem}.{m}.10hz.csv"
        with np.load(files["npz"]) as z:
            user, stream, time, poses, stall = (
                z["user"],
                z["stream"],
                z["time"],
                z["poses"],
                z["stall"],
            )
            names = z["name"]
        for s in data.streams:
            rows = (user == s.user) & (stream == s.stream)
            t = time[rows]
            n = int(np.floor((s.times[-1] - s.times[0]) * 90.0 + 1e-9)) + 1
            assert t.size == n
            np.testing.assert_allclose(t, s.times[0] + np.arange(n) / 90.0, rtol=0, atol=1e-9)
            assert set(names[rows].tolist()) == {s.name}
        norms = np.linalg.norm(poses[:, 3:], axis=1)
        np.testing.assert_allclose(norms, 1.0, atol=1e-9)
        assert stall.mean() < 0.05  # ideal network, one-interval playout
        with open(files["csv"], newline="") as fh:
            rows_csv = list(csv.reader(fh))
        assert rows_csv[0] == [
            "user",
            "stream",
            "name",
            "time",
            "px",
            "py",
            "pz",
            "qw",
            "qx",
            "qy",
            "qz",
            "stall",
        ]
        body = rows_csv[1:]
        assert len(body) == user.size == result["frames_rendered"] // 2
        assert [int(r[0]) for r in body[:50]] == user[:50].tolist()
        vals = np.array([r[3:11] for r in body], dtype=np.float64)
        np.testing.assert_allclose(vals[:, 0], time, atol=5e-7, rtol=0)
        np.testing.assert_allclose(vals[:, 1:4], poses[:, :3], atol=5e-8, rtol=0)
        np.testing.assert_allclose(vals[:, 4:], poses[:, 3:], atol=5e-9, rtol=0)
        assert [int(r[11]) for r in body] == stall.astype(int).tolist()
    summary = json.loads((tmp_path / f"{stem}.replay.10hz.json").read_text())
    assert summary["qoe"].keys() == result["qoe"].keys()


def test_replay_qoe_is_the_scenarios_definition(recording: Path) -> None:
    """The QoE equals evaluate_group on each user's recorded streams, ideal network."""
    methods = ["soa", "dq-slerp", "motor-cubic"]
    result = replay_offline(recording, methods, 12.0, None)
    assert result["files"] == {}
    data = read_session(recording)
    groups = []
    delays: dict[str, list[float]] = {m: [] for m in methods}
    for user in sorted(data.users):
        streams = [s for s in data.streams if s.user == user]
        times = streams[0].times
        truth = Trace(
            "u",
            times,
            np.stack([s.poses for s in streams], 1).astype(float),
            tuple(s.name or "" for s in streams),
        )
        send, idx = sample_keyframes(times, 12.0)
        log = KeyframeLog(times[idx], send, truth.poses[idx])
        for m in methods:
            d = ideal_delay(12.0, truth.native_rate, interp_info(m).lookahead)
            groups.append(evaluate_group(truth, log, d, [m]))
            delays[m].append(d)
    assert result["qoe"] == summarize(groups)
    for m in methods:  # the median over users (their recorded rates differ a little)
        assert min(delays[m]) <= result["delay_s"][m] <= max(delays[m])
    hands = result["qoe"]["soa"]["hands"]
    assert 0 < hands["tip_p50_mm"] < hands["tip_p95_mm"]
    assert result["timing"]["speedup"] > 0
    assert result["session_s"] == pytest.approx(5.0, abs=0.1)


def test_replay_refuses_velocity_methods_and_bad_formats(recording: Path, tmp_path: Path) -> None:
    """A recording without velocities refuses velocity methods; only csv and npz are written."""
    with pytest.raises(ValueError, match="velocities"):
        replay_offline(recording, ["motor-hermite"], 10.0, tmp_path)
    with pytest.raises(ValueError, match="format"):
        replay_offline(recording, ["soa"], 10.0, tmp_path, formats=("parquet",))
    with pytest.raises(KeyError):
        replay_offline(recording, ["nope"], 10.0, tmp_path)


def test_replay_uses_recorded_velocities_for_velocity_methods(tmp_path: Path) -> None:
    """Updates of the velocity variant are recorded, read back bit-exact and drive
    motor-hermite and motor-quintic (a 6-keyframe window) exactly as the QoE definition."""
    path = synthesize_recording(tmp_path, users=2, duration=4.0, seed=2, velocities=True)
    data = read_session(path)
    methods = ["soa", "motor-hermite", "motor-quintic"]
    result = replay_offline(path, methods, 10.0, None)
    groups = []
    for user in sorted(data.users):
        streams = [s for s in data.streams if s.user == user]
        assert all(s.velocities is not None and s.velocities.shape == (len(s), 6) for s in streams)
        times = streams[0].times
        truth = Trace(
            "u",
            times,
            np.stack([s.poses for s in streams], 1).astype(float),
            tuple(s.name or "" for s in streams),
        )
        vel = np.stack([s.velocities for s in streams if s.velocities is not None], 1)
        assert np.isfinite(vel).all() and np.abs(vel).max() > 0
        assert np.array_equal(vel, vel.astype(np.float16).astype(np.float32))  # wire float16
        send, idx = sample_keyframes(times, 10.0)
        log = KeyframeLog(times[idx], send, truth.poses[idx], velocities=vel[idx].astype(float))
        for m in methods:
            d = ideal_delay(10.0, truth.native_rate, interp_info(m).lookahead)
            groups.append(evaluate_group(truth, log, d, [m]))
    assert result["qoe"] == summarize(groups)
    herm = result["qoe"]["motor-hermite"]["hands"]
    assert 0 < herm["tip_p50_mm"] < herm["tip_p95_mm"]


def test_bench_replay_prints_figures(tmp_path: Path) -> None:
    """The benchmark synthesises a session, replays it six ways and reports speed-ups."""
    lines: list[str] = []
    report = bench_replay(
        users=2,
        duration=3.0,
        methods=("soa", "motor-lerp"),
        directory=tmp_path,
        echo=lines.append,
    )
    assert len(report["runs"]) == 6 and len(lines) == 7
    assert all(r["speedup"] > 0 for r in report["runs"])
    assert all("x real time" in line for line in lines[1:])
