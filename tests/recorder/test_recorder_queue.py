"""The relay never waits on the recorder: bounded queue, writer thread, losses recorded."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from reckit import T0, Update, make_updates
from support import wait_until

from posecast.recorder import (
    DropRecord,
    PoseRecord,
    RecorderError,
    SessionReader,
    SessionRecorder,
    info,
    read_records,
)


def _offer(rec: SessionRecorder, updates: list[Update]) -> list[bool]:
    return [
        rec.record_update(u.user, u.seq, u.arrival, u.streams, u.capture_times, u.poses)
        for u in updates
    ]


def test_queue_overflow_is_counted_and_recorded(tmp_path: Path) -> None:
    """With the writer stalled, a full queue loses records; a drops record says how many."""
    updates = make_updates(20)
    rec = SessionRecorder.open(tmp_path, "r", name="o", clock=lambda: T0, queue_size=4)
    rec.hold()
    accepted = _offer(rec, updates[:10])
    assert accepted == [True] * 4 + [False] * 6
    stats = rec.statistics()
    assert stats.queue_drops == 6 and stats.queue_depth == 4
    lost_poses = sum(len(u.streams) for u in updates[4:10])
    assert stats.queue_drop_poses == lost_poses
    rec.release()
    wait_until(lambda: not rec.statistics().queue_depth, every=0.001)
    assert _offer(rec, updates[10:12]) == [True, True]
    path = rec.close()
    assert rec.statistics().loss_records == 1

    records = [r for r in read_records(path) if isinstance(r, PoseRecord | DropRecord)]
    kinds = [r.seq if isinstance(r, PoseRecord) else r.kind for r in records]
    assert kinds == [u.seq for u in updates[:4]] + ["recorder-queue-overflow"] + [
        u.seq for u in updates[10:12]
    ]
    loss = records[4]
    assert isinstance(loss, DropRecord)
    assert loss.data["count"] == 6 and loss.data["poses"] == lost_poses
    assert loss.data["topics"] == {"poses": 6}
    assert loss.data["first_time"] == pytest.approx(updates[4].arrival, abs=1e-9)
    assert loss.data["last_time"] == pytest.approx(updates[9].arrival, abs=1e-9)
    assert info(path)["drops"]["recorder_queue"] == 6


def test_loss_pending_at_close_is_recorded(tmp_path: Path) -> None:
    """Records lost just before close are still reported in the file."""
    rec = SessionRecorder.open(tmp_path, "r", name="c", clock=lambda: T0, queue_size=2)
    rec.hold()
    rec.record_event({"kind": "a"})
    rec.record_event({"kind": "b"})
    assert not rec.record_event({"kind": "c"})
    assert not rec.record_presence({"kind": "join", "user": 1})
    path = rec.close()
    drops = [r for r in read_records(path) if isinstance(r, DropRecord)]
    assert [(d.kind, d.data["count"], d.data["topics"]) for d in drops] == [
        ("recorder-queue-overflow", 2, {"events": 1, "presence": 1})
    ]


def test_writer_keeps_up_with_a_room(tmp_path: Path) -> None:
    """20 users x 20 Hz in 50 ms bursts through a 64-record queue: nothing is lost."""
    updates = make_updates(400, users=20)
    rec = SessionRecorder.open(tmp_path, "r", name="k", clock=lambda: T0, queue_size=64)
    for k in range(0, 400, 20):
        assert all(_offer(rec, updates[k : k + 20]))
        time.sleep(0.05)
    path = rec.close()
    stats = rec.statistics()
    assert stats.queue_drops == 0 and stats.records_written == 401
    assert stats.queue_high_water <= 64
    assert sum(isinstance(r, PoseRecord) for r in read_records(path)) == 400


def test_writer_throughput(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A 10 000-record backlog is written completely; rates are reported, not asserted."""
    updates = make_updates(10_000, users=20)
    rec = SessionRecorder.open(tmp_path, "r", name="t", clock=lambda: T0, queue_size=20_000)
    rec.hold()
    t0 = time.perf_counter()
    assert all(_offer(rec, updates))
    t1 = time.perf_counter()
    rec.release()
    rec.close()
    t2 = time.perf_counter()
    stats = rec.statistics()
    assert stats.records_written == 10_001 and stats.queue_drops == 0
    with capsys.disabled():
        print(
            f"\nrecorder: record_update costs the caller {1e6 * (t1 - t0) / len(updates):.1f} us;"
            f" the writer thread drains {len(updates) / (t2 - t1):,.0f} records/s"
            f" ({stats.poses_written / (t2 - t1):,.0f} poses/s)"
        )


def test_records_after_close_are_rejected(tmp_path: Path) -> None:
    """Records offered after close are refused and counted, never raised."""
    rec = SessionRecorder.open(tmp_path, "r", name="x")
    rec.close()
    assert not rec.record_update(0, 0, 1.0, [0], [1.0], np.zeros((1, 7), np.float32))
    assert not rec.record_event({"kind": "late"})
    assert rec.statistics().rejected == 2
    assert rec.close() == tmp_path / "x.mcap"  # closing twice is harmless


def test_bad_records_are_rejected_not_raised(tmp_path: Path) -> None:
    """Unserialisable events and malformed updates are refused and counted."""
    rec = SessionRecorder.open(tmp_path, "r", name="b")
    assert not rec.record_event({"kind": "x", "obj": object()})
    assert not rec.record_update(0, 0, 1.0, [0, 1], [1.0], np.zeros((1, 7)))
    assert rec.record_event({"kind": "fine"})
    rec.close()
    assert rec.statistics().rejected == 2


def test_writer_failure_keeps_the_part_file(tmp_path: Path) -> None:
    """If writing fails the relay is not affected; close() raises and the .part stays."""
    rec = SessionRecorder.open(tmp_path, "r", name="f", flush_interval=0.01)
    rec.hold()
    rec._file.close()  # the disk goes away under the writer
    rec.release()
    rec.record_event({"kind": "x"})
    wait_until(lambda: rec.failed, limit=10.0, every=0.005)
    assert not rec.record_event({"kind": "after"})
    with pytest.raises(RecorderError):
        rec.close()
    assert rec.part_path.exists() and not rec.path.exists()
    with SessionReader(rec.part_path) as reader:
        assert not reader.complete
        assert reader.session["room"] == "r"


def test_batched_handoff_keeps_every_record_in_order(tmp_path: Path) -> None:
    """With batch_size > 1, every record reaches the file, in order, after poll/close."""
    updates = make_updates(300, users=5)
    rec = SessionRecorder.open(
        tmp_path, "r", name="b", clock=lambda: T0, batch_size=64, batch_delay=3600.0
    )
    assert all(_offer(rec, updates[:100]))
    assert rec.statistics().records_offered < 100  # a partial batch is still waiting
    rec.poll()  # not old enough: stays
    assert all(_offer(rec, updates[100:]))
    path = rec.close()
    stats = rec.statistics()
    assert stats.queue_drops == 0 and stats.records_written == 301
    seqs = [r.seq for r in read_records(path) if isinstance(r, PoseRecord)]
    assert seqs == [u.seq for u in updates]


def test_poll_hands_over_an_aged_batch(tmp_path: Path) -> None:
    """poll() passes a waiting batch to the writer once batch_delay has passed."""
    rec = SessionRecorder.open(
        tmp_path, "r", name="p", clock=lambda: T0, batch_size=64, batch_delay=0.0
    )
    rec.record_event({"kind": "a"})
    rec.poll()
    assert rec.statistics().records_offered == 1
    rec.close()
