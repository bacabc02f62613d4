"""Trace loading: the real vr-traces files and clear errors for bad ones."""

from __future__ import annotations

import gzip
from pathlib import Path

import numpy as np
import pytest

from posecast.scenarios import traces
from posecast.scenarios.traces import TraceError, device_class, find_traces, load_trace


def test_loads_real_dev_trace(dev_trace_path: Path) -> None:
    """A dev trace loads as (N,) times and (N, 3, 7) unit-quaternion poses."""
    tr = load_trace(dev_trace_path)
    assert tr.streams == ("head", "left", "right")
    assert tr.poses.shape == (tr.times.shape[0], 3, 7)
    assert np.all(np.diff(tr.times) > 0)
    np.testing.assert_allclose(np.linalg.norm(tr.poses[..., 3:], axis=-1), 1.0, atol=1e-12)
    assert 70 < tr.native_rate < 95


def test_find_traces_splits(trace_root: Path) -> None:
    """traces:dev and traces:eval resolve to the CSVs of each split."""
    dev = find_traces("traces:dev")
    ev = find_traces("traces:eval")
    assert len(dev) == 7 and len(ev) == 5
    assert all(p.parent.name == "dev" for p in dev)


def test_full_sets_are_bundled(monkeypatch: pytest.MonkeyPatch) -> None:
    """Without POSECAST_TRACES, traces:dev and traces:eval are the sets shipped in the package."""
    monkeypatch.delenv("POSECAST_TRACES", raising=False)
    dev, ev = find_traces("traces:dev"), find_traces("traces:eval")
    assert [p.parent for p in dev] == [traces.BUNDLED_DIR / "dev"] * 7
    assert [p.parent for p in ev] == [traces.BUNDLED_DIR / "eval"] * 5
    assert all(p.name.endswith(".csv.gz") for p in dev + ev)
    names = {load_trace(p).name for p in ev}
    assert names == {
        "S06_quest2link_expertplus_60hz",
        "S07_riftCV1_expert",
        "S08_quest1_expertplus_72hz",
        "S09_quest2_hard",
        "S10_vive_wands_expertplus",
    }
    for licence in ("README.md", "LICENSE-MIT.txt", "LICENSE-BSD-3-Clause.txt"):
        assert (traces.BUNDLED_DIR / licence).is_file()


def test_posecast_traces_wins_when_it_holds_the_split(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, dev_trace_path: Path
) -> None:
    """POSECAST_TRACES with a dev/ folder is read for traces:dev; eval falls back to the bundle."""
    (tmp_path / "dev").mkdir()
    own = tmp_path / "dev" / "mine.csv.gz"
    own.write_bytes(dev_trace_path.read_bytes())
    monkeypatch.setenv("POSECAST_TRACES", str(tmp_path))
    assert find_traces("traces:dev") == [own]
    assert [p.parent for p in find_traces("traces:eval")] == [traces.BUNDLED_DIR / "eval"] * 5


def test_x01_is_lifted_onto_the_floor() -> None:
    """X01's origin is its headset's start: on load every height is raised by FLOOR_LIFTS."""
    lift = traces.FLOOR_LIFTS["X01_quest2_scripted_head"]
    (path,) = [p for p in find_traces("traces:dev") if p.name.startswith("X01")]
    tr = load_trace(path)
    raw = np.loadtxt(path, delimiter=",", skiprows=1)
    np.testing.assert_allclose(tr.poses[:, :, 1], raw[:, 2::7][:, :3] + lift, atol=1e-12)
    assert 1.6 < np.median(tr.poses[:, 0, 1]) < 1.8  # a standing user's head
    assert tr.poses[:, :, 1].min() > 0.0  # nothing under the floor
    # Every other trace loads as written.
    s02 = load_trace(find_traces("traces:sample")[0])
    raw02 = np.loadtxt(find_traces("traces:sample")[0], delimiter=",", skiprows=1)
    np.testing.assert_array_equal(s02.poses[:, :, 1], raw02[:, 2::7][:, :3])


def test_bad_trace_files_give_clear_errors(tmp_path: Path) -> None:
    """Missing, empty, wrong-header and non-monotonic files raise TraceError."""
    with pytest.raises(TraceError, match="no such trace"):
        load_trace(tmp_path / "nope.csv")
    empty = tmp_path / "empty.csv"
    empty.write_text("")
    with pytest.raises(TraceError, match="empty"):
        load_trace(empty)
    bad = tmp_path / "bad.csv"
    bad.write_text("t,a,b\n0,1,2\n")
    with pytest.raises(TraceError, match="unexpected columns"):
        load_trace(bad)
    header = "t," + ",".join(
        f"{d}_{c}"
        for d in ("head", "left", "right")
        for c in ("px", "py", "pz", "qw", "qx", "qy", "qz")
    )
    row = ",0,0,0,1,0,0,0" * 3
    back = tmp_path / "back.csv"
    back.write_text(f"{header}\n1{row}\n0.5{row}\n")
    with pytest.raises(TraceError, match="strictly increasing"):
        load_trace(back)


def test_device_classes() -> None:
    """head is head, left/right are hands, anything else is an object."""
    assert device_class("head") == "head"
    assert device_class("left") == device_class("right") == "hands"
    assert device_class("object:drill") == "objects"


def test_sample_set_is_bundled_and_loads(sample_dir: Path) -> None:
    """traces:sample resolves to the bundled .csv.gz excerpts: real motion, about 60 s each."""
    files = find_traces("traces:sample")
    assert [p.parent for p in files] == [sample_dir] * 4
    assert all(p.name.endswith(".csv.gz") for p in files)
    for p in files:
        tr = load_trace(p)
        assert not tr.name.endswith((".csv", ".gz"))
        assert 59.0 < tr.duration <= 60.0
        assert tr.poses.shape == (tr.times.size, 3, 7)
    assert (sample_dir / "README.md").is_file() and (sample_dir / "LICENSE-MIT.txt").is_file()


def test_gzip_and_plain_csv_load_alike(dev_trace_path: Path, tmp_path: Path) -> None:
    """A trace reads the same from .csv and .csv.gz, and takes the same name."""
    plain = tmp_path / "S02_riftS_expertplus.csv"
    plain.write_bytes(gzip.decompress(dev_trace_path.read_bytes()))
    a, b = load_trace(plain), load_trace(dev_trace_path)
    assert a.name == b.name == "S02_riftS_expertplus"
    np.testing.assert_array_equal(a.times, b.times)
    np.testing.assert_array_equal(a.poses, b.poses)
    assert find_traces(tmp_path) == [plain]


def test_sample_is_the_start_of_the_full_dev_trace(dev_trace_path: Path) -> None:
    """The bundled excerpt holds the full dev recording's first 60 s, bit for bit."""
    (path,) = [p for p in find_traces("traces:dev") if p.name.startswith("S02_")]
    full = load_trace(path)
    part = load_trace(dev_trace_path)
    np.testing.assert_array_equal(full.window(0.0, 60.0).times, part.times)
    np.testing.assert_array_equal(full.window(0.0, 60.0).poses, part.poses)


def test_missing_full_sets_say_how_to_point_at_them(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """traces:dev/eval missing (a trimmed install, POSECAST_TRACES empty): one line naming
    POSECAST_TRACES and traces:sample."""
    monkeypatch.setenv("POSECAST_TRACES", str(tmp_path / "nowhere"))
    monkeypatch.setattr(traces, "BUNDLED_DIR", tmp_path / "trimmed")
    for split in ("dev", "eval"):
        with pytest.raises(TraceError) as err:
            find_traces(f"traces:{split}")
        text = str(err.value)
        assert "\n" not in text
        assert f"'{split}'" in text and "POSECAST_TRACES" in text and "traces:sample" in text
    with pytest.raises(TraceError, match="unknown trace set"):
        find_traces("traces:devv")


def test_not_a_trace_file_is_one_clear_error(tmp_path: Path) -> None:
    """A directory, a binary file or a broken gzip give a TraceError, not a traceback."""
    with pytest.raises(TraceError, match="directory"):
        load_trace(tmp_path)
    junk = tmp_path / "junk.csv.gz"
    junk.write_bytes(b"\x1f\x8b\x08\x00garbage")
    with pytest.raises(TraceError, match="not a numeric trace CSV"):
        load_trace(junk)
    binary = tmp_path / "bin.csv"
    binary.write_bytes(bytes(range(256)))
    with pytest.raises(TraceError):
        load_trace(binary)
