"""The writer-process recorder: same file as the thread recorder, losses recorded, crash-safe."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import numpy as np
import pytest
from reckit import T0, make_updates
from support import wait_until

from posecast.protocol import PoseUpdate, decode_message, encode_message
from posecast.recorder import (
    DropRecord,
    EventRecord,
    PoseRecord,
    PresenceRecord,
    ProcessRecorder,
    RecorderError,
    RecorderHost,
    SessionReader,
    SessionRecorder,
    pipe,
    read_records,
    recover,
)

Update = tuple[int, float, PoseUpdate]


def _updates(count: int, seed: int = 0) -> list[Update]:
    """(user, arrival, update) as the relay decodes them from the frames it receives."""
    out = []
    for u in make_updates(count, seed=seed):
        poses = u.poses.astype(np.float64)
        poses[:, 3:] /= np.linalg.norm(poses[:, 3:], axis=1, keepdims=True)
        msg = decode_message(
            encode_message(PoseUpdate.from_arrays(u.seq, u.streams, u.capture_times, poses))
        )
        assert isinstance(msg, PoseUpdate)
        out.append((u.user, u.arrival, msg))
    return out


def _feed(rec: ProcessRecorder | SessionRecorder, updates: list[Update]) -> None:
    for k, (user, arrival, update) in enumerate(updates):
        assert rec.record_pose_update(user, arrival, update)
        if k % 40 == 0:
            rec.record_presence({"kind": "rate", "user": user, "rate": 20.0}, arrival)
            rec.record_event({"kind": "grab", "user": user, "object": k}, arrival)
        rec.poll()


def _content(path: Path) -> list[tuple[object, ...]]:
    rows: list[tuple[object, ...]] = []
    for r in read_records(path):
        if isinstance(r, PoseRecord):
            rows.append(
                (
                    "pose",
                    r.user,
                    r.seq,
                    r.arrival,
                    r.streams.tobytes(),
                    r.capture_times.tobytes(),
                    r.poses.tobytes(),
                )
            )
        elif isinstance(r, PresenceRecord | EventRecord | DropRecord):
            rows.append((type(r).__name__, r.time, sorted(r.data.items())))
    return rows


def test_process_recorder_writes_what_the_thread_recorder_writes(tmp_path: Path) -> None:
    """Same frames and records into both recorders: the same records, bit for bit."""
    frames = _updates(400)
    proc = ProcessRecorder.open(tmp_path / "p", "r", name="s", clock=lambda: T0, batch_size=32)
    assert proc.part_path.exists() and proc.part_path.name == "s.mcap.part"
    _feed(proc, frames)
    path_p = proc.close(T0 + 30)
    thread = SessionRecorder.open(tmp_path / "t", "r", name="s", clock=lambda: T0)
    _feed(thread, frames)
    path_t = thread.close(T0 + 30)

    assert path_p.name == "s.mcap" and not proc.part_path.exists()
    got, want = _content(path_p), _content(path_t)
    assert len([g for g in got if g[0] == "pose"]) == 400
    assert got == want
    stats = proc.statistics()
    assert stats.closed and stats.error is None
    assert stats.records_offered == 400 + 2 * 10
    assert stats.records_written == stats.records_offered + 1  # + the recording-start event
    assert stats.poses_written == sum(len(f[2].entries) for f in frames)
    assert stats.queue_drops == 0 and stats.rejected == 0 and stats.fsyncs >= 1
    assert stats.bytes_written == path_p.stat().st_size
    with SessionReader(path_p) as reader:
        assert reader.session["writer"] == "process"


def test_a_full_queue_loses_batches_counts_them_and_records_the_loss(tmp_path: Path) -> None:
    frames = _updates(200)
    rec = ProcessRecorder.open(
        tmp_path, "r", name="o", clock=lambda: T0, queue_size=8, batch_size=4
    )
    rec.hold()  # the pipe is not written: 8 records (2 batches) may wait, then batches are lost
    for user, arrival, update in frames[:40]:
        rec.record_pose_update(user, arrival, update)
    stats = rec.statistics()
    assert stats.records_offered == 8 and stats.queue_drops == 32 and stats.queue_depth == 8
    lost = [f for f in frames[stats.records_offered : 40]]
    assert stats.queue_drop_poses == sum(len(f[2].entries) for f in lost)
    rec.release()
    for k in (40, 44, 48):
        wait_until(lambda: not rec.statistics().queue_depth, every=0.001)
        for user, arrival, update in frames[k : k + 4]:  # one batch each
            rec.record_pose_update(user, arrival, update)
    path = rec.close()
    assert rec.statistics().loss_records == 1
    records = [r for r in read_records(path) if isinstance(r, PoseRecord | DropRecord)]
    kept = stats.records_offered
    assert [r.seq for r in records[:kept] if isinstance(r, PoseRecord)] == [
        f[2].seq for f in frames[:kept]
    ]
    loss = records[kept]
    assert isinstance(loss, DropRecord) and loss.kind == "recorder-queue-overflow"
    assert loss.data["count"] == len(lost) and loss.data["poses"] == stats.queue_drop_poses
    assert loss.data["topics"] == {"poses": len(lost)}
    assert loss.data["first_time"] == pytest.approx(lost[0][1], abs=1e-9)
    assert loss.data["last_time"] == pytest.approx(lost[-1][1], abs=1e-9)
    assert len(records) == kept + 1 + 12


def test_when_the_relay_vanishes_the_child_keeps_a_recoverable_part(tmp_path: Path) -> None:
    """The pipe closes without a stop (the server was SIGKILLed): nothing taken is lost."""
    frames = _updates(300)
    rec = ProcessRecorder.open(tmp_path, "r", name="c", clock=lambda: T0, batch_size=16)
    _feed(rec, frames)
    rec._handoff()
    rec.host.drain(block=True)  # everything is in the pipe; now close it as a dying process does
    proc = rec.host.process
    assert proc.stdin is not None
    proc.stdin.close()
    assert proc.wait(30) == 2
    assert proc.stdout is not None
    proc.stdout.close()
    assert rec.part_path.exists() and not rec.path.exists()
    out = tmp_path / "recovered.mcap"
    report = recover(rec.part_path, out)
    assert report.chunks_lost == 0 and not report.complete
    poses = [r for r in read_records(out) if isinstance(r, PoseRecord)]
    assert [(r.user, r.seq) for r in poses] == [(f[0], f[2].seq) for f in frames]


def test_a_dead_writer_process_fails_the_recorder_not_the_relay(tmp_path: Path) -> None:
    frames = _updates(100)
    rec = ProcessRecorder.open(tmp_path, "r", name="d", clock=lambda: T0, batch_size=4)
    _feed(rec, frames[:20])
    os.kill(rec.host.process.pid, signal.SIGKILL)
    rec.host.process.wait(10)

    def failed() -> bool:
        for user, arrival, update in frames[20:40]:
            rec.record_pose_update(user, arrival, update)  # never raises, never blocks
        rec.poll()
        return rec.failed

    wait_until(failed, limit=10.0, every=0.01)
    assert rec.failed and "recorder process" in (rec.statistics().error or "")
    assert not rec.record_pose_update(*frames[50])
    with pytest.raises(RecorderError, match="partial file kept"):
        rec.close()
    assert rec.part_path.exists()


def test_bad_records_are_refused_and_counted(tmp_path: Path) -> None:
    rec = ProcessRecorder.open(tmp_path, "r", name="b", clock=lambda: T0)
    assert not rec.record_update(1, 0, T0, [1, 2], [T0], np.zeros((2, 7)))
    assert not rec.record_event({"bad": object()}, T0)
    # An update whose entries do not match its header (the relay never sends
    # one) reaches the child, which refuses and counts it.
    bad = pipe._UPDATE.pack(pipe._KIND_UPDATE, pipe._UPDATE_EXTRA + 5, 1, 1, T0, 0, T0)
    rec._batch.parts += (bad, b"short")
    rec._batch.records += 1
    path = rec.close(T0 + 1)
    stats = rec.statistics()
    assert stats.rejected == 3
    assert not [r for r in read_records(path) if isinstance(r, PoseRecord)]


def test_open_fails_clearly_when_the_folder_cannot_be_written(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.raises(RecorderError, match="did not start"):
        ProcessRecorder.open(blocker / "sub", "r")


# -- one writer process for many rooms ------------------------------------------------


def test_one_host_records_many_rooms_each_into_its_own_file(tmp_path: Path) -> None:
    """Three rooms fed interleaved through one writer process: each file holds exactly
    its room's records, in order, bit for bit what a thread recorder writes."""
    feeds = [_updates(150, seed=s) for s in range(3)]
    extra = _updates(20, seed=9)
    with RecorderHost.start() as host:
        rooms = [
            host.open_room(tmp_path / "p", f"r{i}", name=f"s{i}", clock=lambda: T0, batch_size=7)
            for i in range(3)
        ]
        assert host.rooms == 3 and {r.host.pid for r in rooms} == {host.pid}
        for k in range(150):
            for rec, feed in zip(rooms, feeds, strict=True):
                user, arrival, update = feed[k]
                assert rec.record_pose_update(user, arrival, update)
                if k % 40 == 0:
                    rec.record_event({"kind": "grab", "user": user, "object": k}, arrival)
                rec.poll()
        # Closing one room leaves the others recording through the same process.
        paths = [rooms[1].close(T0 + 60)]
        assert host.alive and host.rooms == 2
        for user, arrival, update in extra:
            rooms[0].record_pose_update(user, arrival, update)
        paths += [rooms[0].close(T0 + 60), rooms[2].close(T0 + 60)]
        assert host.rooms == 0
    assert host.close() == 0
    for i, path in zip((1, 0, 2), paths, strict=True):
        assert path.exists() and path.name == f"s{i}.mcap"
        thread = SessionRecorder.open(tmp_path / "t", f"r{i}", name=f"s{i}", clock=lambda: T0)
        for k, (user, arrival, update) in enumerate(feeds[i]):
            thread.record_pose_update(user, arrival, update)
            if k % 40 == 0:
                thread.record_event({"kind": "grab", "user": user, "object": k}, arrival)
        if i == 0:
            for user, arrival, update in extra:
                thread.record_pose_update(user, arrival, update)
        expected = thread.close(T0 + 60)
        assert _content(path) == _content(expected)
        assert rooms[i].statistics().queue_drops == 0


def test_a_room_that_cannot_open_or_goes_bad_leaves_the_other_rooms_alone(
    tmp_path: Path,
) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    frames = _updates(60)
    with RecorderHost.start() as host:
        good = host.open_room(tmp_path, "good", name="good", clock=lambda: T0, batch_size=4)
        with pytest.raises(RecorderError, match="did not start room 'bad'"):
            host.open_room(blocker / "sub", "bad")
        bad = host.open_room(tmp_path, "corrupt", name="corrupt", clock=lambda: T0, batch_size=4)
        # A message of an unknown kind inside one room's batch fails that room only.
        bad._batch.parts += (pipe._HEAD.pack(99, 3), b"abc")
        bad._batch.records += 1
        bad._handoff()
        _feed(good, frames)
        wait_until(lambda: bad.failed, limit=20.0, every=0.01)
        assert bad.failed and "unknown message kind 99" in (bad.statistics().error or "")
        assert not bad.record_pose_update(*frames[0])
        with pytest.raises(RecorderError, match="partial file kept"):
            bad.close()
        assert host.alive
        path = good.close(T0 + 60)
        assert good.statistics().queue_drops == 0 and not good.failed
    poses = [r for r in read_records(path) if isinstance(r, PoseRecord)]
    assert [(r.user, r.seq) for r in poses] == [(f[0], f[2].seq) for f in frames]


def test_when_the_relay_vanishes_every_open_room_keeps_a_recoverable_part(
    tmp_path: Path,
) -> None:
    feeds = [_updates(100, seed=s) for s in range(2)]
    host = RecorderHost.start()
    rooms = [host.open_room(tmp_path, f"r{i}", name=f"v{i}", clock=lambda: T0) for i in range(2)]
    for rec, feed in zip(rooms, feeds, strict=True):
        _feed(rec, feed)
        rec._handoff()
    host.drain(block=True)
    proc = host.process
    assert proc.stdin is not None
    proc.stdin.close()  # as a dying relay's pipe closes
    assert proc.wait(30) == pipe.EXIT_RELAY_GONE
    host.close()
    for rec, feed in zip(rooms, feeds, strict=True):
        assert rec.part_path.exists() and not rec.path.exists()
        out = tmp_path / f"recovered-{rec.part_path.name}.mcap"
        report = recover(rec.part_path, out)
        assert report.chunks_lost == 0
        poses = [r for r in read_records(out) if isinstance(r, PoseRecord)]
        assert [(r.user, r.seq) for r in poses] == [(f[0], f[2].seq) for f in feed]


def test_a_stalled_writer_fails_a_blocking_drain_instead_of_hanging(tmp_path: Path) -> None:
    """A writer process that takes nothing (a stalled disk; here SIGSTOP) cannot hang
    a closing room or the server's shutdown: the blocking drain gives up and says why."""
    host = RecorderHost.start()
    rec = host.open_room(tmp_path, "s", name="s", clock=lambda: T0)
    os.kill(host.pid, signal.SIGSTOP)
    try:
        more_than_the_pipe = 2 << 20
        blob = pipe._frame(pipe._FRAME_BATCH, rec.room_id, more_than_the_pipe)
        with host.lock:
            host.push_locked(rec.room_id, blob + bytes(more_than_the_pipe), 1)
        host.drain(block=True, timeout=1.0)
        assert rec.failed and "took no records for 1 s" in (rec.statistics().error or "")
        assert not host.alive and rec.statistics().queue_depth == 0
    finally:
        os.kill(host.pid, signal.SIGCONT)
    with pytest.raises(RecorderError, match="partial file kept"):
        rec.close()
    assert host.close() == pipe.EXIT_RELAY_GONE  # the room never finished: .part kept
    assert rec.part_path.exists()
