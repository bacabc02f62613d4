"""``posecast export``: times relative, wall-clock or as recorded; a z-up world for
Foxglove; each file names its time base and frame. Runs the real executable."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from test_cli_mistakes import assert_one_line, posecast

from posecast.recorder.export import read_session
from posecast.recorder.replay import synthesize_recording


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return synthesize_recording(tmp_path_factory.mktemp("rec"), users=2, rate=30.0, duration=1.0)


def _session(path: Path) -> dict[str, str]:
    with path.open("rb") as fh:
        return next(
            m.metadata for m in make_reader(fh).iter_metadata() if m.name == "posecast.session"
        )


def _csv(folder: Path) -> tuple[list[dict[str, object]], np.ndarray]:
    index = json.loads((folder / "streams.json").read_text())
    rows = np.loadtxt(folder / index[0]["file"], delimiter=",", skiprows=1)
    return index, rows


def test_csv_times_default_to_relative_and_say_so(recording: Path, tmp_path: Path) -> None:
    """CSV: relative times by default (server time minus the header's start), y-up."""
    session = _session(recording)
    for name, args in (("rel", ()), ("srv", ("--time", "server")), ("wall", ("--time", "wall"))):
        res = posecast("export", recording, "--to", "csv", "--out", tmp_path / name, *args)
        assert res.code == 0, res.stderr
    rel_index, rel = _csv(tmp_path / "rel")
    _, srv = _csv(tmp_path / "srv")
    _, wall = _csv(tmp_path / "wall")
    start, start_wall = float(session["start_time"]), float(session["start_wall_time"])
    assert rel_index[0]["time"] == "relative" and rel_index[0]["frame"] == "world"
    np.testing.assert_allclose(rel[:, 0], srv[:, 0] - start, atol=1e-6)
    np.testing.assert_allclose(wall[:, 0], srv[:, 0] - start + start_wall, atol=1e-6)
    np.testing.assert_array_equal(rel[:, 1:], srv[:, 1:])  # poses untouched


def _turn(v: np.ndarray, q: np.ndarray) -> np.ndarray:
    """v turned by the unit quaternion q (w first)."""
    w, u = q[0], q[1:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def test_z_up_turns_the_world_and_names_the_frame(recording: Path, tmp_path: Path) -> None:
    """--z-up: p -> (x, -z, y); each device's axes turn the same way; frame world_z_up."""
    for name, frame in (("y", "--y-up"), ("z", "--z-up")):
        res = posecast("export", recording, "--to", "csv", "--out", tmp_path / name, frame)
        assert res.code == 0, res.stderr
    _, y = _csv(tmp_path / "y")
    index, z = _csv(tmp_path / "z")
    assert index[0]["frame"] == "world_z_up" and "+z up" in str(index[0]["frame_axes"])
    np.testing.assert_allclose(z[:, 1:4], np.stack([y[:, 1], -y[:, 3], y[:, 2]], 1), atol=2e-6)
    for row_y, row_z in zip(y[::7], z[::7], strict=True):
        for axis in np.eye(3):  # a device axis, seen in each world
            seen_y, seen_z = _turn(axis, row_y[4:8]), _turn(axis, row_z[4:8])
            np.testing.assert_allclose(seen_z, [seen_y[0], -seen_y[2], seen_y[1]], atol=2e-6)


def test_foxglove_defaults_to_wall_times_and_z_up(recording: Path, tmp_path: Path) -> None:
    """Foxglove: wall-clock timestamps and log times, parent frame world_z_up, the
    posecast.export metadata saying both."""
    out = tmp_path / "fox.mcap"
    res = posecast("export", recording, "--to", "foxglove", "--out", out)
    assert res.code == 0, res.stderr
    assert "wall times" in res.stdout and "z-up" in res.stdout
    session = _session(recording)
    shift = float(session["start_wall_time"]) - float(session["start_time"])
    with out.open("rb") as fh:
        reader = make_reader(fh)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        *_, (_, _, last) = reader.iter_messages(topics=["/user1/head"])
    assert meta["posecast.export"]["time"] == "wall"
    assert meta["posecast.export"]["frame"] == "world_z_up"
    msg = json.loads(last.data)
    assert msg["parent_frame_id"] == "world_z_up"
    stamp = msg["timestamp"]["sec"] + msg["timestamp"]["nsec"] / 1e9
    assert math.isclose(last.log_time / 1e9, stamp, abs_tol=1e-6)
    head = next(st for st in read_session(recording).streams if (st.user, st.name) == (1, "head"))
    assert math.isclose(stamp, float(head.times.max()) + shift, abs_tol=1e-6)


def test_a_bad_time_base_is_one_line(recording: Path) -> None:
    assert_one_line(
        posecast("export", recording, "--to", "csv", "--time", "utc"), 2, "--time", "utc"
    )
