"""The core's tick schedule across rooms, the link's rate adaptation, failed rooms.

Sans-I/O like ``test_core.py``: the time is an argument, nothing sleeps.
"""

from __future__ import annotations

import pytest
from test_core import connect, recorded

from posecast.protocol import SetRate
from posecast.scenarios.network import Tier
from posecast.server.actions import PollRecording
from posecast.server.core import Close, FinishRecording, RelayCore, Reschedule, ServerConfig
from posecast.server.room import Room


def brute_deadline(core: RelayCore) -> float | None:
    dues = [d for d in (r.next_due() for r in core.rooms.values()) if d is not None]
    return min(dues) if dues else None


def test_next_deadline_follows_joins_rates_leaves_and_ticks() -> None:
    """The earliest due time over all rooms, whatever moved it (earlier or later)."""
    core = RelayCore()
    clients = [
        connect(core, 1.0, room=f"r{i % 4}", rate=(5.0, 10.0, 20.0)[i % 3]) for i in range(12)
    ]
    now = 1.0
    for step in range(200):
        assert core.next_deadline() == brute_deadline(core)
        if step == 50:
            clients[3].send(SetRate(rate=30.0), now)  # sooner
        if step == 80:
            clients[5].send(SetRate(rate=5.0), now)  # later
        if step in (100, 120, 140):
            core.disconnect(clients.pop().conn, now)
        due = core.next_deadline()
        assert due is not None and due > now
        now = due
        core.tick(now)
    for c in clients:
        core.disconnect(c.conn, now)
    assert core.next_deadline() is None and core.rooms == {}


def test_a_tick_looks_only_at_the_rooms_due(monkeypatch: pytest.MonkeyPatch) -> None:
    """A wake-up costs the due room, not a scan of every room's members (O(n^2) a tick)."""
    core = RelayCore()
    for i in range(40):
        connect(core, 1.0, room=f"r{i}", rate=20.0)  # 40 rooms, 40 phases
    calls = 0
    original = Room.next_due

    def counted(self: Room) -> float | None:
        nonlocal calls
        calls += 1
        return original(self)

    monkeypatch.setattr(Room, "next_due", counted)
    due = core.next_deadline()
    assert due is not None
    core.tick(due)
    core.next_deadline()
    assert calls <= 6  # the due room's entries, checked and re-queued; never the 39 others


def test_a_rate_the_link_lowers_in_take_is_not_left_unannounced() -> None:
    """take() adapting the rate to the emulated link hands a Reschedule to the adapter."""
    tier = Tier(
        "slow", max_rate_hz=30.0, bandwidth_kbps=8.0, latency_ms=50.0, jitter_ms=0.0, loss_pct=0.0
    )
    core = RelayCore(ServerConfig(link=tier))
    pub, sub = connect(core, 1.0, rate=30.0), connect(core, 1.0, rate=30.0)
    pub.read(1.0)
    pub.publish(1.01)
    due = core.next_deadline()
    assert due is not None
    core.tick(due)
    core.take(sub.conn, due)
    member = core.rooms["lobby"].members[sub.user]
    assert member.rate < 30.0  # the link's cap
    assert Reschedule() in core.pending()
    assert core.pending() == []
    assert core.next_deadline() == brute_deadline(core)


def test_a_failed_room_closes_1011_and_its_recording_is_finished_once() -> None:
    """A room whose tick raises: members closed with 1011, the others go on; the recording
    is finished when its last member is gone, once, and the name can be used again."""
    core = RelayCore()
    assert core.add_room("bad", True, 0.5)
    a, b = connect(core, 1.0, room="bad"), connect(core, 1.0, room="bad")
    ok = connect(core, 1.0, room="good")
    bad = core.rooms["bad"]

    def explode(now: float, out: object = None) -> int:
        raise RuntimeError("a bug")

    bad.tick = explode  # type: ignore[method-assign]
    actions: list[object] = []
    for _ in range(3):
        due = core.next_deadline()
        assert due is not None
        actions += core.tick(due)
    closes = [x for x in actions if isinstance(x, Close)]
    assert sorted((x.conn, x.code) for x in closes) == [(a.conn, 1011), (b.conn, 1011)]
    assert "bad" not in core.rooms and "good" in core.rooms
    first = core.disconnect(a.conn, 2.0)
    assert not [x for x in first if isinstance(x, FinishRecording)]
    last = core.disconnect(b.conn, 2.1)
    assert [x for x in last if isinstance(x, FinishRecording)] == [FinishRecording("bad")]
    presence = recorded([*a.actions, *b.actions, *first, *last], "presence", "bad")
    assert [r["kind"] for r in presence] == ["join", "join", "leave", "leave"]
    assert not [x for x in core.close_rooms(3.0) if isinstance(x, FinishRecording)]
    assert not [x for x in core.disconnect(ok.conn, 3.1) if isinstance(x, FinishRecording)]


def test_after_close_rooms_no_room_is_added_or_finished_twice() -> None:
    """Shutdown finishes every recorded room once; a recorder opened late is refused."""
    core = RelayCore()
    assert core.add_room("lobby", True, 0.5)
    a = connect(core, 1.0)
    assert core.close_rooms(2.0) == [PollRecording("lobby"), FinishRecording("lobby")]
    assert not [x for x in core.disconnect(a.conn, 2.1) if isinstance(x, FinishRecording)]
    assert not core.add_room("late", True, 2.2)
    assert core.rooms == {} and core.next_deadline() is None
