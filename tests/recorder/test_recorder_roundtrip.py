"""Writing a session and reading it back: records, time ranges, arrays, info."""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np
import pytest
from reckit import T0, Update, make_updates, write_session

from posecast.recorder import (
    DropRecord,
    EventRecord,
    PoseRecord,
    PresenceRecord,
    SessionReader,
    SessionRecorder,
    format_info,
    info,
    load_streams,
    read_records,
)


def _assert_same_update(rec: PoseRecord, u: Update) -> None:
    assert (rec.user, rec.seq, rec.arrival) == (u.user, u.seq, u.arrival)
    assert np.array_equal(rec.streams, u.streams)
    assert np.array_equal(rec.capture_times, u.capture_times)
    assert rec.poses.dtype == np.float32
    assert np.array_equal(rec.poses.view(np.uint32), u.poses.view(np.uint32))


def test_round_trip_is_bit_exact(tmp_path: Path) -> None:
    """Every update, event, presence and drop record reads back exactly, in arrival order."""
    updates = make_updates(600)
    rec = SessionRecorder.open(tmp_path, "room", name="s", clock=lambda: T0)
    rec.record_presence({"kind": "join", "user": 0, "streams": {"head": 0}}, time=T0)
    for i, u in enumerate(updates):
        assert rec.record_update(u.user, u.seq, u.arrival, u.streams, u.capture_times, u.poses)
        if i % 100 == 0:
            rec.record_event({"kind": "grab", "user": u.user, "object": "cube"}, time=u.arrival)
            rec.record_drop({"kind": "flood", "user": u.user, "count": 2, "time": u.arrival})
    rec.record_presence({"kind": "leave", "user": 0, "reason": "left"}, time=updates[-1].arrival)
    path = rec.close()
    assert path == tmp_path / "s.mcap" and path.exists()
    assert not (tmp_path / "s.mcap.part").exists()

    records = read_records(path)
    poses = [r for r in records if isinstance(r, PoseRecord)]
    assert len(poses) == len(updates)
    for r, u in zip(poses, updates, strict=True):
        _assert_same_update(r, u)
    events = [r for r in records if isinstance(r, EventRecord)]
    drops = [r for r in records if isinstance(r, DropRecord)]
    presence = [r for r in records if isinstance(r, PresenceRecord)]
    assert [e.kind for e in events] == ["recording-start"] + ["grab"] * 6
    # JSON records carry their time as the MCAP log time: nanosecond resolution
    expect = [updates[i].arrival for i in range(0, 600, 100)]
    assert [e.time for e in events[1:]] == pytest.approx(expect, abs=1e-9, rel=0)
    assert [(d.kind, d.data["count"]) for d in drops] == [("flood", 2)] * 6
    assert [p.kind for p in presence] == ["join", "leave"]
    stats = rec.statistics()
    assert stats.closed and stats.error is None
    assert stats.records_written == len(records) == 1 + 600 + 12 + 2
    assert stats.poses_written == sum(len(u.streams) for u in updates)
    assert stats.queue_drops == 0 and stats.rejected == 0
    assert stats.bytes_written == path.stat().st_size


def test_seek_by_time(tmp_path: Path) -> None:
    """records(start, end) gives exactly the records with start <= arrival < end."""
    updates = make_updates(400)
    path = write_session(tmp_path, updates, chunk_records=37)
    start, end = updates[100].arrival, updates[250].arrival
    got = [r for r in read_records(path, start, end) if isinstance(r, PoseRecord)]
    assert [r.seq for r in got] == [u.seq for u in updates[100:250]]
    assert [r.user for r in got] == [u.user for u in updates[100:250]]
    with SessionReader(path) as reader:
        late = list(reader.poses(start=updates[-1].arrival))
        assert len(late) == 1
        assert reader.events(end=T0 - 1) == []


def test_load_streams_gives_arrays_with_names(tmp_path: Path) -> None:
    """Per (user, stream): capture times, arrival times and float32 poses, named from presence."""
    updates = make_updates(300, users=3)
    path = write_session(tmp_path, updates)
    streams = load_streams(path)
    for (user, sid), s in streams.items():
        expect = [
            (u.capture_times[j], u.arrival, u.poses[j])
            for u in updates
            if u.user == user
            for j in range(len(u.streams))
            if u.streams[j] == sid
        ]
        assert len(s) == len(expect)
        assert np.array_equal(s.times, [e[0] for e in expect])
        assert np.array_equal(s.arrival, [e[1] for e in expect])
        assert s.poses.dtype == np.float32 and s.poses.shape == (len(expect), 7)
        assert np.array_equal(s.poses, np.array([e[2] for e in expect]))
        assert s.name == ("head", "left", "right")[sid - 3 * user]
        assert s.user_name == f"bot{user}"
    with SessionReader(path) as reader:
        head = reader.load_stream(1, "head")
        assert head.stream == 3 and len(head) == 100
        only = reader.load_streams(users=[2], start=updates[150].arrival)
        assert set(only) == {(2, 6), (2, 7), (2, 8)}
        with pytest.raises(KeyError):
            reader.load_stream(1, "tail")


def test_info_reports_users_streams_rates_sizes_and_drops(tmp_path: Path) -> None:
    """info() lists users, per-stream keyframes/s, bytes per pose and drop counts."""
    updates = make_updates(400, users=4)
    rec = SessionRecorder.open(tmp_path, "lobby", name="i", clock=lambda: T0)
    rec.record_presence(
        {"kind": "join", "user": 0, "name": "ann", "streams": {"head": 0, "left": 1}, "rate": 20},
        time=T0,
    )
    for u in updates:
        rec.record_update(u.user, u.seq, u.arrival, u.streams, u.capture_times, u.poses)
    rec.record_drop({"kind": "skip", "user": 0, "count": 3}, time=updates[10].arrival)
    rec.record_drop({"kind": "flood", "user": 1}, time=updates[20].arrival)
    path = rec.close()
    data = info(path)
    assert data["room"] == "lobby" and data["complete"] is True
    assert data["records"] == {"drops": 2, "events": 1, "poses": 400, "presence": 1}
    assert data["drops"]["by_kind"] == {"flood": 1, "skip": 3}
    assert data["drops"]["total"] == 4 and data["drops"]["missing_records"] == 0
    ann = next(u for u in data["users"] if u["user"] == 0)
    assert ann["name"] == "ann" and ann["streams"] == {"0": "head", "1": "left"}
    head = next(s for s in data["streams"] if (s["user"], s["stream"]) == (0, 0))
    assert head["name"] == "head" and head["keyframes"] == 100
    assert head["rate"] == pytest.approx(20.0, rel=0.05)
    poses = sum(len(u.streams) for u in updates)
    assert data["sizes"]["poses"] == poses
    assert data["sizes"]["bytes_per_pose"] == pytest.approx(path.stat().st_size / poses)
    text = format_info(data)
    assert "lobby" in text and "ann" in text and "B/pose" in text and "skip 3" in text


def test_session_metadata(tmp_path: Path) -> None:
    """The file names the room, version, start time and users present at the start."""
    users = [{"user": 5, "name": "eve", "streams": {"head": 9}, "rate": 10.0}]
    rec = SessionRecorder.open(
        tmp_path, "meta room", clock=lambda: 42.0, wall_clock=lambda: 1.7e9, users=users
    )
    assert rec.record_update(5, 0, 42.5, [9], [42.4], np.zeros((1, 7), np.float32))
    path = rec.close(time=43.0)
    assert path.name == "meta-room-20231114T221320Z.mcap"
    with SessionReader(path) as reader:
        assert reader.profile == "posecast"
        assert reader.session["room"] == "meta room"
        assert float(reader.session["start_time"]) == 42.0
        assert reader.metadata["posecast.session.end"]["end_time"] == "43.0"
        eve = reader.users()[5]
        assert (eve.name, eve.streams, eve.rate) == ("eve", {9: "head"}, 10.0)
        assert reader.load_stream(5, "head").name == "head"


def test_names_never_collide(tmp_path: Path) -> None:
    """Two recordings of one room in the same second get different files."""
    a = SessionRecorder.open(tmp_path, "r", wall_clock=lambda: 0.0)
    b = SessionRecorder.open(tmp_path, "r", wall_clock=lambda: 0.0)
    assert a.close() != b.close()
    assert len(list(tmp_path.glob("*.mcap"))) == 2


def test_unfinished_file_reads_linearly(tmp_path: Path) -> None:
    """A .part being written is readable (every closed chunk) without recovery."""
    updates = make_updates(100)
    rec = SessionRecorder.open(tmp_path, "live", name="live", clock=lambda: T0, chunk_records=10)
    for u in updates:
        rec.record_update(u.user, u.seq, u.arrival, u.streams, u.capture_times, u.poses)
    rec.hold()  # queue drained; chunks of 10 records closed (the 101st record is pending)
    try:
        with SessionReader(rec.part_path) as reader:
            assert not reader.complete
            got = list(reader.poses())
            assert [p.seq for p in got] == [u.seq for u in updates[: len(got)]]
            assert len(got) in (99, 100)
            assert reader.session["room"] == "live"
    finally:
        rec.release()
        rec.close()


async def test_aclose_from_the_event_loop(tmp_path: Path) -> None:
    """aclose() finishes the file without blocking the event loop."""
    rec = SessionRecorder.open(tmp_path, "async", name="a")
    ticks = 0

    async def ticker() -> None:
        nonlocal ticks
        while True:
            ticks += 1
            await asyncio.sleep(0)

    task = asyncio.create_task(ticker())
    rec.record_event({"kind": "scene", "step": 1})
    path = await rec.aclose()
    task.cancel()
    assert path.exists() and ticks > 0
    assert [e.data.get("step") for e in read_records(path) if isinstance(e, EventRecord)] == [
        None,
        1,
    ]
