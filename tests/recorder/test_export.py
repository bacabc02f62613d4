"""Exports of a recording: CSV, NPZ, Foxglove MCAP; the fast reader and the CSV writer."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from posecast.recorder import SessionReader
from posecast.recorder.export import (
    FRAME_TRANSFORM_SCHEMA,
    csv_bytes,
    export,
    read_session,
    stream_label,
)
from posecast.recorder.replay import synthesize_recording


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three users x 3 streams x 30 Hz x 3 s from the dev traces."""
    return synthesize_recording(tmp_path_factory.mktemp("rec"), users=3, duration=3.0)


def _reference(path: Path) -> dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Every stream via SessionReader, sorted by capture time: (times, arrival, poses)."""
    with SessionReader(path) as r:
        found = r.load_streams()
    out = {}
    for key, s in found.items():
        o = np.argsort(s.times, kind="stable")
        out[key] = (s.times[o], s.arrival[o], s.poses[o])
    return out


def test_fast_reader_equals_the_session_reader(recording: Path, tmp_path: Path) -> None:
    """read_session gives SessionReader's streams, names and users, bit for bit."""
    ref = _reference(recording)
    with SessionReader(recording) as r:
        users = r.users()
    # The same file read through the fallback path (a .part name reads via SessionReader).
    part = tmp_path / "copy.mcap.part"
    shutil.copy(recording, part)
    for data in (read_session(recording), read_session(part)):
        assert data.users == users
        assert data.session["room"] == "synthetic"
        assert [(s.user, s.stream) for s in data.streams] == sorted(ref)
        for s in data.streams:
            times, arrival, poses = ref[(s.user, s.stream)]
            assert np.array_equal(s.times, times) and np.array_equal(s.arrival, arrival)
            assert np.array_equal(s.poses.view(np.uint32), poses.view(np.uint32))
            assert s.name == users[s.user].streams[s.stream]


def test_csv_export_has_one_file_per_stream(recording: Path, tmp_path: Path) -> None:
    """One CSV per stream (time + 7 pose columns) within print precision, and an index."""
    out = export(recording, "csv", tmp_path / "csv")
    index = json.loads((out / "streams.json").read_text())
    ref = _reference(recording)
    assert len(index) == len(ref) == 9
    for entry in index:
        with (out / entry["file"]).open(newline="") as fh:
            rows = list(csv.reader(fh))
        assert rows[0] == ["time", "px", "py", "pz", "qw", "qx", "qy", "qz"]
        values = np.array(rows[1:], dtype=np.float64)
        times, _arr, poses = ref[(entry["user"], entry["stream"])]
        assert values.shape == (times.size, 8) == (entry["keyframes"], 8)
        np.testing.assert_allclose(values[:, 0], times, atol=1e-9, rtol=0)
        np.testing.assert_allclose(values[:, 1:4], poses[:, :3], atol=1e-7, rtol=0)
        np.testing.assert_allclose(values[:, 4:], poses[:, 3:], atol=1e-8, rtol=0)


def test_npz_export_is_bit_exact(recording: Path, tmp_path: Path) -> None:
    """The NPZ holds every stream's times, arrivals and float32 poses unchanged."""
    out = export(recording, "npz", tmp_path / "session")
    assert out.name == "session.npz"
    ref = _reference(recording)
    data = read_session(recording)
    with np.load(out) as z:
        index = json.loads(str(z["streams"]))
        assert len(index) == len(ref)
        for s in data.streams:
            label = stream_label(s)
            times, arrival, poses = ref[(s.user, s.stream)]
            assert np.array_equal(z[f"{label}.time"], times)
            assert np.array_equal(z[f"{label}.arrival"], arrival)
            assert z[f"{label}.poses"].dtype == np.float32
            assert np.array_equal(z[f"{label}.poses"].view(np.uint32), poses.view(np.uint32))


def test_recorded_velocities_are_exported(tmp_path: Path) -> None:
    """Velocity-variant updates: both readers agree, CSV gets vx..wz, NPZ the float32 array."""
    path = synthesize_recording(tmp_path / "rec", users=2, duration=2.0, velocities=True)
    with SessionReader(path) as r:
        ref = r.load_streams()
    data = read_session(path)
    for s in data.streams:
        want = ref[(s.user, s.stream)]
        assert s.velocities is not None and want.velocities is not None
        o = np.argsort(want.times, kind="stable")
        assert np.array_equal(s.velocities, want.velocities[o])
    out = export(path, "csv", tmp_path / "csv")
    entry = json.loads((out / "streams.json").read_text())[0]
    with (out / entry["file"]).open(newline="") as fh:
        rows = list(csv.reader(fh))
    assert rows[0][8:] == ["vx", "vy", "vz", "wx", "wy", "wz"]
    s = next(x for x in data.streams if (x.user, x.stream) == (entry["user"], entry["stream"]))
    assert s.velocities is not None
    np.testing.assert_allclose(
        np.array(rows[1:], dtype=np.float64)[:, 8:], s.velocities, atol=5e-8, rtol=0
    )
    npz = export(path, "npz", tmp_path / "v")
    with np.load(npz) as z:
        assert np.array_equal(z[f"{stream_label(s)}.velocities"], s.velocities)


def test_foxglove_export_uses_the_frame_transform_schema(recording: Path, tmp_path: Path) -> None:
    """An MCAP of JSON foxglove.FrameTransform channels, one per stream, values as recorded."""
    out = export(recording, "foxglove", tmp_path / "fox")
    assert out.suffix == ".mcap"
    ref = _reference(recording)
    with out.open("rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None
        assert len(summary.channels) == len(ref) == 9
        assert {s.name for s in summary.schemas.values()} == {"foxglove.FrameTransform"}
        for schema in summary.schemas.values():
            assert schema.encoding == "jsonschema"
            assert json.loads(schema.data) == FRAME_TRANSFORM_SCHEMA
        for ch in summary.channels.values():
            assert ch.message_encoding == "json"
        seen: dict[str, list[dict[str, object]]] = {}
        log_times = []
        for _schema, channel, message in reader.iter_messages(log_time_order=False):
            msg = json.loads(message.data)
            seen.setdefault(channel.topic, []).append(msg)
            log_times.append(message.log_time)
            ts = msg["timestamp"]
            assert message.log_time == ts["sec"] * 1_000_000_000 + ts["nsec"]
    assert log_times == sorted(log_times)  # one timeline, in capture-time order
    users = read_session(recording).users
    for (user, sid), (times, _arr, poses) in ref.items():
        name = users[user].streams[sid]
        msgs = seen[f"/user{user}/{name}"]
        assert len(msgs) == times.size
        first = msgs[0]
        assert first["parent_frame_id"] == "world"
        assert first["child_frame_id"] == f"user{user}/{name}"
        p = poses[0].tolist()
        assert first["translation"] == {"x": p[0], "y": p[1], "z": p[2]}
        assert first["rotation"] == {"x": p[4], "y": p[5], "z": p[6], "w": p[3]}
        stamps = [m["timestamp"]["sec"] + m["timestamp"]["nsec"] / 1e9 for m in msgs]  # type: ignore[index]
        np.testing.assert_allclose(stamps, times, atol=1e-9, rtol=0)


def test_export_refuses_an_unknown_format(recording: Path, tmp_path: Path) -> None:
    """Only csv, npz and foxglove are known."""
    with pytest.raises(ValueError, match="unknown export format"):
        export(recording, "parquet", tmp_path / "x")  # type: ignore[arg-type]


def test_csv_bytes_prints_like_printf() -> None:
    """Fixed-point columns read back within half a unit of the last digit, like %.Nf."""
    rng = np.random.default_rng(3)
    n = 2000
    x = rng.normal(size=n) * np.logspace(-9, 5, n)
    x[:4] = [0.0, -0.0, -4e-9, 123456789.5]
    q = rng.uniform(-1, 1, n)
    ids = rng.integers(0, 70000, n)
    names = np.array([b"head", b"object:ball"])[np.arange(n) % 2]
    data = csv_bytes(("x", "q", "id", "name"), [x, q, ids, names], (4, 8, None, None))
    lines = data.decode().splitlines()
    assert lines[0] == "x,q,id,name"
    rows = [line.split(",") for line in lines[1:]]
    assert len(rows) == n
    assert [r[2] for r in rows] == [str(i) for i in ids.tolist()]
    assert [r[3] for r in rows] == [b.decode() for b in names.tolist()]
    for col, values, dec in ((0, x, 4), (1, q, 8)):
        text = [r[col] for r in rows]
        assert all(len(t.split(".")[1]) == dec for t in text)
        back = np.array(text, dtype=np.float64)
        np.testing.assert_allclose(back, values, rtol=1e-15, atol=0.5 * 10.0**-dec * (1 + 1e-9))
        want = [f"{v:.{dec}f}" for v in values.tolist()]
        want = [w.lstrip("-") if float(w) == 0 else w for w in want]  # no "-0.0000"
        same = np.mean([t == w for t, w in zip(text, want, strict=True)])
        assert same > 0.99  # differences only where printf's tie rounding differs
    assert rows[1][0] == rows[2][0] == "0.0000"  # -0.0 and -4e-9 print without a sign


def test_csv_bytes_falls_back_for_non_finite_values() -> None:
    """NaN and inf print as Python prints them."""
    data = csv_bytes(("a",), [np.array([1.5, np.nan, -np.inf])], (2,))
    assert data.decode().splitlines() == ["a", "1.50", "nan", "-inf"]
