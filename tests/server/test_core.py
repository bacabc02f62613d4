"""The relay's rules on the sans-I/O core: no sockets, no tasks, no sleeps.

A test drives :class:`server.core.RelayCore` the way the asyncio adapter does,
with real protocol bytes from a :class:`protocol.ClientSession` per client and
the time as an argument, and reads what the core decided from its actions and
from the frames :meth:`RelayCore.take` hands out.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import msgpack
import numpy as np
import pytest

from posecast.protocol import (
    Bye,
    ClientSession,
    ErrorMessage,
    Hello,
    Join,
    Joined,
    PeerJoined,
    PeerLeft,
    Ping,
    Pong,
    PoseUpdate,
    SetRate,
    Snapshot,
    UserEvent,
    Welcome,
)
from posecast.server.actions import Record, RecordPose
from posecast.server.auth import make_token
from posecast.server.core import Close, FinishRecording, RelayCore, Reschedule, ServerConfig, Wake

POSE = np.array([[0.0, 1.6, 0.0, 1.0, 0.0, 0.0, 0.0]] * 3)


@dataclass
class Client:
    """One client: its protocol session, connection id and what it received."""

    core: RelayCore
    conn: int
    session: ClientSession = field(default_factory=ClientSession)
    inbox: list[object] = field(default_factory=list)
    user: int = -1
    streams: dict[str, int] = field(default_factory=dict)
    seq: int = 0
    #: Every action the core returned for what this client sent, in order.
    actions: list[object] = field(default_factory=list)

    def send(self, message: object, now: float, wall: float = 0.0) -> list[object]:
        data = self.session.send(message)  # type: ignore[arg-type]
        out = list(self.core.receive(self.conn, data, now, wall))
        self.actions.extend(out)
        return out

    def read(self, now: float) -> list[object]:
        """Decode whatever the core has for this connection now."""
        frames, _ = self.core.take(self.conn, now)
        got: list[object] = []
        for data in frames:
            got.extend(self.session.receive_data(data))
        for event in got:
            if isinstance(event, Welcome):
                self.user = event.user
            if isinstance(event, Joined):
                self.streams = dict(event.streams)
        self.inbox.extend(got)
        return got

    def publish(self, now: float, capture: float | None = None) -> list[object]:
        self.seq += 1
        ids = list(self.streams.values())
        t = now if capture is None else capture
        update = PoseUpdate.from_arrays(self.seq, ids, np.full(len(ids), t), POSE)
        return self.send(update, now)


def connect(core: RelayCore, now: float, room: str = "lobby", rate: float = 10.0) -> Client:
    c = Client(core, core.connect(now))
    c.send(Hello(agent="t"), now)
    c.read(now)
    c.send(Join(room=room, streams=("head", "left", "right"), rate=rate), now)
    c.read(now)
    return c


def test_hello_join_and_peers_both_ways() -> None:
    """A second member learns the first (peer_joined) and the first learns it."""
    core = RelayCore()
    a = connect(core, 1.0)
    b = connect(core, 1.1)
    assert a.user != b.user and len(a.streams) == len(b.streams) == 3
    assert set(a.streams.values()).isdisjoint(b.streams.values())
    joined_b = [e for e in b.inbox if isinstance(e, PeerJoined)]
    assert [e.user for e in joined_b] == [a.user]
    assert not [e for e in a.read(1.1) if isinstance(e, PeerJoined)]  # at the room's tick
    core.tick(1.1)
    joined_a = [e for e in a.read(1.1) if isinstance(e, PeerJoined)]
    assert [e.user for e in joined_a] == [b.user] and joined_a[0].streams == b.streams
    assert core.rooms["lobby"].members.keys() == {a.user, b.user}


def test_one_snapshot_encoded_per_tick_group() -> None:
    """Two due members of one rate get the very same bytes; the sender its own streams too."""
    core = RelayCore()
    a, b = connect(core, 1.0), connect(core, 1.0)
    first = core.next_deadline()
    assert first is not None
    core.tick(first)  # presence notices out
    a.read(first)
    b.read(first)
    a.publish(first + 0.01)
    due = core.next_deadline()
    assert due is not None and due > first + 0.01
    actions = core.tick(due)
    assert {x.conn for x in actions if isinstance(x, Wake)} == {a.conn, b.conn}
    fa, _ = core.take(a.conn, due)
    fb, _ = core.take(b.conn, due)
    assert len(fa) == len(fb) == 1 and fa[0] is fb[0]
    (snap,) = b.session.receive_data(fb[0])
    assert isinstance(snap, Snapshot) and sorted(snap.entries["stream"].tolist()) == sorted(
        a.streams.values()
    )


def test_latest_wins_and_a_skip_is_counted() -> None:
    """A snapshot not taken before the next tick is replaced (a skip), never queued."""
    core = RelayCore()
    a, b = connect(core, 1.0), connect(core, 1.0)
    a.read(1.0)
    a.publish(1.01)
    t1 = core.next_deadline()
    assert t1 is not None
    core.tick(t1)
    a.publish(t1 + 0.01)
    t2 = core.next_deadline()
    assert t2 is not None and t2 > t1
    core.tick(t2)
    frames, _ = core.take(b.conn, t2)
    assert len(frames) == 1
    assert core.peer(b.conn).statistics().skips == 1


def test_update_flood_is_dropped_then_closed() -> None:
    """Over max_update_rate a second is dropped and counted; 10 s worth closes with 1008."""
    core = RelayCore(ServerConfig(max_update_rate=10.0))
    a = connect(core, 1.0)
    for _ in range(10):
        a.publish(1.0)
    assert core.peer(a.conn).flood_drops == 0
    closes: list[object] = []
    for _ in range(101):
        closes += [x for x in a.publish(1.0) if isinstance(x, Close)]
    assert core.peer(a.conn).flood_drops == 101
    assert closes == [Close(a.conn, 1008, "update flood: over 10 updates/s")]
    # An hour later the bucket is full again: updates are admitted (no new close).
    assert not [x for x in a.publish(3601.0) if isinstance(x, Close)]


def test_bad_frame_gets_an_error_and_the_close_code() -> None:
    """Garbage is a fatal bad-frame: an error message, then close 1002; text frames too."""
    core = RelayCore()
    a = connect(core, 1.0)
    actions = core.receive(a.conn, b"\xc1\xc1 not msgpack", 1.0)
    closes = [x for x in actions if isinstance(x, Close)]
    assert len(closes) == 1 and closes[0].code == 1002
    frames, _ = core.take(a.conn, 1.0)
    assert b"bad-frame" in frames[-1]
    t = Client(core, core.connect(2.0))
    (close,) = [x for x in core.receive(t.conn, "hello", 2.0) if isinstance(x, Close)]
    assert close.code == 1002 and "text frames" in close.reason
    # What a closing connection still sends is counted, not handled.
    assert core.receive(a.conn, b"\x00", 1.1) == []
    assert core.peer(a.conn).frames_in == 4  # hello, join, garbage, and the last


def test_nonfatal_error_keeps_the_session() -> None:
    """A bad rate is refused with bad-rate; the session goes on."""
    core = RelayCore()
    a = connect(core, 1.0)
    # (a ClientSession refuses to send it: raw bytes, as a hostile peer would)
    actions = core.receive(a.conn, msgpack.packb({"type": "set_rate", "rate": 500.0}), 1.0)
    assert not [x for x in actions if isinstance(x, Close)]
    errors = [e for e in a.read(1.0) if isinstance(e, ErrorMessage)]
    assert [e.code for e in errors] == ["bad-rate"]


def test_tokens_are_checked_with_the_wall_time() -> None:
    """With a secret, a missing or expired token is unauthorized (1008); a good one joins."""
    core = RelayCore(ServerConfig(secret="s3cret"))
    good = make_token("s3cret", "lobby", "alice", ttl=60.0, now=1000.0)
    a = Client(core, core.connect(1.0))
    a.send(Hello(), 1.0)
    a.read(1.0)
    a.send(Join(room="lobby", streams=("head",), rate=10.0, token=good), 1.0, wall=1030.0)
    assert any(isinstance(e, Joined) for e in a.read(1.0))
    assert core.peer(a.conn).name == "alice"
    late = Client(core, core.connect(1.0))
    late.send(Hello(), 1.0)
    late.read(1.0)
    actions = late.send(
        Join(room="lobby", streams=("head",), rate=10.0, token=good), 1.0, wall=2000.0
    )
    assert [x.code for x in actions if isinstance(x, Close)] == [1008]
    errors = [e for e in late.read(1.0) if isinstance(e, ErrorMessage)]
    assert [e.code for e in errors] == ["unauthorized"]
    assert len(core.rooms["lobby"].members) == 1


def test_events_reach_the_others_in_order() -> None:
    """An event goes to every other member, in order, stamped with the sender's id."""
    core = RelayCore()
    a, b, c = connect(core, 1.0), connect(core, 1.0), connect(core, 1.0)
    for x in (a, b, c):
        x.read(1.0)
    for i in range(3):
        a.send(UserEvent(kind="button", payload={"i": i}), 1.0)
    for x in (b, c):
        got = [e for e in x.read(1.0) if isinstance(e, UserEvent)]
        assert [e.payload for e in got] == [{"i": 0}, {"i": 1}, {"i": 2}]
        assert {e.user for e in got} == {a.user}
    assert not [e for e in a.read(1.0) if isinstance(e, UserEvent)]


def test_a_slow_reader_is_closed_alone() -> None:
    """An event queue that overflows closes that member with 1008 too-slow; others go on."""
    core = RelayCore(ServerConfig(max_event_queue=4, max_update_rate=1000.0))
    a, slow, ok = connect(core, 1.0), connect(core, 1.0), connect(core, 1.0)
    a.read(1.0)
    closes: list[Close] = []
    for i in range(8):
        closes += [
            x
            for x in a.send(UserEvent(kind="button", payload={"i": i}), 1.0)
            if isinstance(x, Close)
        ]
        ok.read(1.0)  # this one keeps up
    assert [(c.conn, c.code) for c in closes] == [(slow.conn, 1008)]
    assert "too-slow" in closes[0].reason
    assert len([e for e in ok.inbox if isinstance(e, UserEvent)]) == 8


def test_leaving_tells_the_room_and_removes_it_when_empty() -> None:
    """A disconnect sends peer_left to the rest; the last one out removes the room."""
    core = RelayCore()
    a, b = connect(core, 1.0), connect(core, 1.0)
    core.tick(1.5)  # b is announced to a (a join and leave within one tick would not be)
    a.read(1.5)
    actions = core.disconnect(b.conn, 2.0)
    assert Reschedule() in actions
    core.tick(2.0)  # presence notices go out at the room's tick
    assert [e.user for e in a.read(2.0) if isinstance(e, PeerLeft)] == [b.user]
    core.disconnect(a.conn, 3.0)
    assert "lobby" not in core.rooms and core.next_deadline() is None
    assert core.closed_connections == 2 and core.totals["frames_in"] > 0


def test_a_recorded_room_is_finished_when_removed() -> None:
    """A recorded room's joins, updates and leaves are actions to record; an empty
    recorded room is to be finished, after its last records."""
    core = RelayCore()
    assert core.add_room("lobby", True, 0.5)
    assert not core.add_room("lobby", False, 0.5)
    a = connect(core, 1.0)
    poses = [x for x in a.publish(1.0) if isinstance(x, RecordPose)]
    assert [(x.room, x.user, x.now) for x in poses] == [("lobby", a.user, 1.0)]
    assert [r["kind"] for r in recorded(a.actions, "presence")] == ["join"]
    actions = core.disconnect(a.conn, 2.0)
    assert [r["kind"] for r in recorded(actions, "presence")] == ["leave"]
    assert actions[-1] == FinishRecording("lobby")


def recorded(
    actions: Iterable[object], topic: str, room: str | None = None
) -> list[dict[str, Any]]:
    """The records of ``topic`` the core said to write (in ``room``), in order."""
    return [
        x.record
        for x in actions
        if isinstance(x, Record) and x.topic == topic and room in (None, x.room)
    ]


def test_set_rate_moves_the_grid() -> None:
    """A member asking 30 Hz instead of 5 Hz is due sooner; the change asks for a reschedule."""
    core = RelayCore()
    a = connect(core, 1.0, rate=5.0)
    before = core.next_deadline()
    actions = a.send(SetRate(rate=30.0), 1.0)
    after = core.next_deadline()
    assert Reschedule() in actions
    assert before is not None and after is not None and after < before
    assert after - 1.0 <= 1 / 30 + 1e-9


def test_ping_is_answered_with_server_time_and_bye_closes() -> None:
    """A pong carries the time the ping arrived; bye closes with 1000."""
    core = RelayCore()
    a = connect(core, 1.0)
    a.send(Ping(seq=7, time=0.5), 42.0)
    (pong,) = [e for e in a.read(42.0) if isinstance(e, Pong)]
    assert (pong.seq, pong.ping_time, pong.recv_time) == (7, 0.5, 42.0)
    actions = a.send(Bye(reason="done"), 43.0)
    assert [x for x in actions if isinstance(x, Close)] == [Close(a.conn, 1000, "done")]


@pytest.mark.parametrize("stale_by", [0.0, 0.5])
def test_older_keyframes_are_stale(stale_by: float) -> None:
    """A keyframe not newer than the stored one is counted stale and not relayed."""
    core = RelayCore()
    a, b = connect(core, 1.0), connect(core, 1.0)
    a.publish(2.0, capture=2.0)
    a.publish(2.0, capture=2.0 - stale_by)
    room = core.rooms["lobby"]
    assert room.statistics().stale_updates == 3
    t = core.next_deadline()
    assert t is not None
    core.tick(t)
    (frame,) = core.take(b.conn, t)[0]
    (snap,) = b.session.receive_data(frame)
    assert isinstance(snap, Snapshot)
    # (capture times travel as float32 offsets from the snapshot's time)
    np.testing.assert_allclose(snap.capture_times, np.full(3, 2.0), atol=1e-6)
