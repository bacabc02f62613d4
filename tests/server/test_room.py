"""Room and Outbox without sockets: tick grid, latest-wins ingest, delta snapshots, fan-out."""

from __future__ import annotations

import numpy as np
import pytest

from posecast.protocol import PoseUpdate, Snapshot, decode_message
from posecast.server.actions import Action, Wake
from posecast.server.room import IdAllocator, Member, Outbox, Room, room_phase

IDENTITY = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)


def pose(x: float) -> list[float]:
    """A pose at (x, 0, 0) with the identity rotation."""
    return [x, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]


def update(streams: list[int], capture: list[float], xs: list[float], seq: int = 0) -> PoseUpdate:
    return PoseUpdate.from_arrays(seq, streams, capture, [pose(x) for x in xs])


def snapshot(data: bytes | None) -> Snapshot:
    assert data is not None
    snap = decode_message(data)
    assert isinstance(snap, Snapshot)
    return snap


def contents(data: bytes | None) -> dict[tuple[int, int], float]:
    """(user, stream) -> x of every pose in a snapshot frame."""
    snap = snapshot(data)
    return {
        (int(u), int(s)): float(p[0])
        for u, s, p in zip(snap.users, snap.streams, snap.poses, strict=True)
    }


def member(room: Room, user: int, names: tuple[str, ...], rate: float) -> Member:
    outbox = Outbox()
    return Member(user, f"u{user}", room.allocate_streams(names), rate, outbox)


def test_grid_first_tick_is_next_grid_point() -> None:
    """A member added at t is first due at the next k/rate grid point strictly after t."""
    room = Room("r")
    m = member(room, 1, ("head",), 10.0)
    room.add(m, 0.012)
    assert m.next_due == pytest.approx(0.1)
    assert room.next_due() == pytest.approx(0.1)
    room.add(member(room, 2, ("head",), 20.0), 0.012)
    assert room.next_due() == pytest.approx(0.05)


def test_grid_tick_only_when_due_and_skips_missed_points() -> None:
    """tick() serves only due members; a late tick sends once and resumes on the grid."""
    room = Room("r")
    pub = member(room, 1, ("head",), 10.0)
    sub = member(room, 2, ("head",), 10.0)
    room.add(pub, 0.0)
    room.add(sub, 0.0)
    sid = pub.streams["head"]
    room.ingest(1, update([sid], [0.01], [1.0]))
    assert room.tick(0.05) == 0
    assert sub.outbox.pose is None
    assert room.tick(0.1) == 2  # both members are due; each gets the stream
    assert sub.next_due == pytest.approx(0.2)
    sub.outbox.take()
    room.ingest(1, update([sid], [0.2], [2.0]))
    # 0.2 and 0.3 were missed: one snapshot, no burst, next due at 0.4.
    assert room.tick(0.35) == 2
    assert sub.next_due == pytest.approx(0.4)
    assert sub.outbox.skips == 0
    stats = room.statistics()
    assert stats.tick_lag_max_ms == pytest.approx(150.0)
    assert stats.ticks == 4


def test_no_snapshot_without_news() -> None:
    """A due member whose streams are all unchanged gets no snapshot at all."""
    room = Room("r")
    pub = member(room, 1, ("head",), 10.0)
    room.add(pub, 0.0)
    room.ingest(1, update([pub.streams["head"]], [0.01], [1.0]))
    assert room.tick(0.1) == 1
    pub.outbox.take()
    assert room.tick(0.2) == 0
    assert pub.outbox.pose is None


def test_set_rate_moves_member_to_new_grid() -> None:
    """set_rate puts the member on the grid of its new rate from now on."""
    room = Room("r")
    m = member(room, 1, ("head",), 10.0)
    room.add(m, 0.0)
    room.set_rate(1, 25.0, 0.13)
    assert m.rate == 25.0
    assert m.next_due == pytest.approx(0.16)


def test_ingest_latest_wins_and_counts_stale() -> None:
    """An update older than (or as old as) the stored keyframe is dropped and counted stale."""
    room = Room("r")
    pub = member(room, 1, ("head", "left"), 10.0)
    room.add(pub, 0.0)
    head, left = pub.streams["head"], pub.streams["left"]
    assert room.ingest(1, update([head, left], [0.05, 0.05], [1.0, 1.0])) == 0
    assert room.ingest(1, update([head, left], [0.04, 0.06], [2.0, 2.0])) == 1
    assert room.ingest(1, update([head], [0.05], [3.0])) == 1  # same capture time: stale too
    room.tick(0.1)
    assert contents(pub.outbox.take()) == {(1, head): 1.0, (1, left): 2.0}
    stats = room.statistics()
    assert stats.updates_in == 3
    assert stats.stale_updates == 2
    assert pub.updates_in == 3


def test_delta_snapshot_only_changed_streams() -> None:
    """A member's snapshot holds only the streams that changed since its last snapshot."""
    room = Room("r")
    pub = member(room, 1, ("head", "left", "right"), 10.0)
    sub = member(room, 2, ("head",), 10.0)
    room.add(pub, 0.0)
    room.add(sub, 0.0)
    ids = [pub.streams[n] for n in ("head", "left", "right")]
    room.ingest(1, update(ids, [0.01] * 3, [1.0, 1.0, 1.0]))
    room.tick(0.1)
    assert set(contents(sub.outbox.take())) == {(1, i) for i in ids}
    room.ingest(1, update([ids[1]], [0.15], [2.0]))
    room.tick(0.2)
    assert contents(sub.outbox.take()) == {(1, ids[1]): 2.0}


def test_new_member_gets_every_stream() -> None:
    """A member that joins later gets every stream in its first snapshot, old ones included."""
    room = Room("r")
    pub = member(room, 1, ("head", "left"), 10.0)
    old = member(room, 2, ("head",), 10.0)
    room.add(pub, 0.0)
    room.add(old, 0.0)
    head, left = pub.streams["head"], pub.streams["left"]
    room.ingest(1, update([head, left], [0.01, 0.01], [1.0, 1.0]))
    room.ingest(2, update([old.streams["head"]], [0.01], [5.0]))
    room.tick(0.1)
    old.outbox.take()
    room.ingest(1, update([head], [0.15], [2.0]))
    new = member(room, 3, ("head",), 10.0)
    room.add(new, 0.15)
    room.tick(0.2)
    assert contents(old.outbox.take()) == {(1, head): 2.0}
    assert contents(new.outbox.take()) == {
        (1, head): 2.0,
        (1, left): 1.0,
        (2, old.streams["head"]): 5.0,
    }


def test_same_rate_members_share_one_encoding() -> None:
    """Members in step at one rate receive the very same bytes object; others a separate one."""
    room = Room("r")
    a = member(room, 1, ("head",), 10.0)
    b = member(room, 2, ("head",), 10.0)
    c = member(room, 3, ("head",), 5.0)
    for m in (a, b, c):
        room.add(m, 0.0)
    room.ingest(1, update([a.streams["head"]], [0.01], [1.0]))
    room.tick(0.1)
    first_a, first_b = a.outbox.take(), b.outbox.take()
    assert first_a is not None and first_a is first_b
    assert room.statistics().snapshots_encoded == 1
    room.ingest(1, update([a.streams["head"]], [0.15], [2.0]))
    room.tick(0.2)  # a, b at 10 Hz and c at 5 Hz are due, with different deltas
    assert a.outbox.pose is b.outbox.pose
    assert c.outbox.pose is not a.outbox.pose
    assert contents(c.outbox.pose) == contents(a.outbox.pose)
    assert room.statistics().snapshots_encoded == 3


def test_snapshot_carries_capture_time_and_pose() -> None:
    """The snapshot's capture times and float32 poses are those of the ingested update."""
    room = Room("r")
    pub = member(room, 1, ("head",), 10.0)
    room.add(pub, 100.0)
    sid = pub.streams["head"]
    sent = update([sid], [100.0123], [0.123456789])
    room.ingest(1, sent)
    room.tick(100.1)
    snap = snapshot(pub.outbox.take())
    assert snap.send_time == pytest.approx(100.1)
    assert np.array_equal(snap.poses.view(np.uint32), sent.poses.view(np.uint32))
    dt = abs(float(sent.capture_times[0]) - snap.send_time)
    assert abs(float(snap.capture_times[0]) - float(sent.capture_times[0])) <= dt * 2**-23


def test_skipped_snapshot_content_is_not_lost() -> None:
    """When an unsent snapshot is replaced, the newer one still carries the replaced streams."""
    room = Room("r")
    pub = member(room, 1, ("head", "left"), 10.0)
    sub = member(room, 2, ("head",), 10.0)
    room.add(pub, 0.0)
    room.add(sub, 0.0)
    head, left = pub.streams["head"], pub.streams["left"]
    room.ingest(1, update([head, left], [0.01, 0.01], [1.0, 1.0]))
    room.tick(0.1)  # sub's writer never takes this one
    room.ingest(1, update([head], [0.15], [2.0]))  # left stops moving
    room.tick(0.2)
    assert sub.outbox.skips == 1
    assert contents(sub.outbox.take()) == {(1, head): 2.0, (1, left): 1.0}
    # Once a snapshot went out, deltas resume from it.
    room.ingest(1, update([head], [0.25], [3.0]))
    room.tick(0.3)
    assert contents(sub.outbox.take()) == {(1, head): 3.0}


def test_congested_member_skips_then_gets_everything() -> None:
    """A congested outbox gets no snapshot (counted); once drained it gets all it missed."""
    room = Room("r")
    pub = member(room, 1, ("head", "left"), 10.0)
    sub = Member(2, "u2", room.allocate_streams(("head",)), 10.0, Outbox(8, buffered=100_000))
    room.add(pub, 0.0)
    room.add(sub, 0.0)
    head, left = pub.streams["head"], pub.streams["left"]
    room.ingest(1, update([head, left], [0.01, 0.01], [1.0, 1.0]))
    room.tick(0.1)
    room.ingest(1, update([head], [0.15], [2.0]))
    room.tick(0.2)
    assert sub.outbox.pose is None
    assert sub.congestion_skips == 2
    sub.outbox.buffered = 0  # (the adapter reported the socket drained)
    room.tick(0.3)
    assert contents(sub.outbox.take()) == {(1, head): 2.0, (1, left): 1.0}
    assert sub.outbox.skips == 0
    assert room.statistics().skips == 2 + pub.outbox.skips


def test_remove_drops_streams_and_frees_ids() -> None:
    """A removed member's streams leave the store; later snapshots never carry them."""
    room = Room("r")
    a = member(room, 1, ("head",), 10.0)
    b = member(room, 2, ("head",), 10.0)
    room.add(a, 0.0)
    room.add(b, 0.0)
    room.ingest(1, update([a.streams["head"]], [0.01], [1.0]))
    room.ingest(2, update([b.streams["head"]], [0.01], [2.0]))
    assert room.remove(1) is a
    assert room.remove(1) is None
    assert room.statistics().streams == 1
    room.tick(0.1)
    assert contents(b.outbox.take()) == {(2, b.streams["head"]): 2.0}


def test_outbox_latest_wins_counts_skips() -> None:
    """An unsent snapshot replaced by a newer one is a skip; take() returns the newest."""
    box = Outbox()
    box.offer_snapshot(b"one")
    box.offer_snapshot(b"two")
    box.offer_snapshot(b"three")
    assert box.skips == 2
    assert box.snapshots_offered == 3
    assert box.take() == b"three"
    assert box.take() is None


def test_outbox_events_bounded_and_first() -> None:
    """Events queue in order up to max_events, ahead of the snapshot; overflow is refused."""
    box = Outbox(max_events=3)
    box.offer_snapshot(b"snap")
    assert all(box.offer_event(bytes([i])) for i in range(3))
    assert not box.offer_event(b"x")
    assert len(box.events) == 3
    assert [box.take() for _ in range(5)] == [b"\x00", b"\x01", b"\x02", b"snap", None]


def test_outbox_congested_follows_buffer() -> None:
    """congested() is true exactly when the buffered bytes exceed congested_bytes."""
    box = Outbox(buffered=10, congested_bytes=10)
    assert not box.congested()
    box.buffered = 11
    assert box.congested()


def test_id_allocator_reuses_oldest_freed_only_when_exhausted() -> None:
    """Ids count up; freed ids come back oldest first, only once fresh ones run out."""
    ids = IdAllocator(limit=3)
    assert [ids.take() for _ in range(3)] == [0, 1, 2]
    ids.give_back(2)
    ids.give_back(0)
    assert len(ids) == 1
    assert [ids.take(), ids.take()] == [2, 0]
    with pytest.raises(RuntimeError):
        ids.take()


def test_a_tick_wakes_the_member_it_offers_a_snapshot() -> None:
    """The room never waits: the due time is a number, a tick an offer its owner hears of."""
    room = Room("r")
    pub = member(room, 1, ("head",), 30.0)
    pub.outbox.conn = 7  # (its connection: a tick's offer returns Wake(7))
    woken: list[Action] = []
    room.add(pub, 10.0)
    due = room.next_due()
    assert due is not None and 10.0 < due <= 10.0 + 1 / 30 + 1e-9
    room.ingest(1, update([pub.streams["head"]], [10.0], [1.0]))
    assert room.tick(due - 0.001, woken) == 0 and woken == []  # not due yet
    assert room.tick(due, woken) == 1 and woken == [Wake(7)]
    assert contents(pub.outbox.take()) == {(1, pub.streams["head"]): 1.0}
    room.remove(1)
    assert room.next_due() is None
    room.retire()
    assert room.retired


def test_room_phase_offsets_the_tick_grid() -> None:
    """A room with a phase ticks on (k + phase) / rate; phases come from the name."""
    room = Room("p", phase=0.25)
    m = member(room, 1, ("head",), 10.0)
    room.add(m, 0.0)
    assert m.next_due == pytest.approx(0.025)
    room.tick(0.025)
    assert m.next_due == pytest.approx(0.125)
    assert 0.0 <= room_phase("lobby") < 1.0
    assert room_phase("lobby") == room_phase("lobby") != room_phase("demo")
