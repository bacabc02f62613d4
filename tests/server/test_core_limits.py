"""One bad peer cannot hurt a room: the core's limits and misbehaviour budget.

Sans-I/O like ``test_core.py``: the time is an argument, nothing sleeps.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_core import POSE, Client, connect, recorded

from posecast.protocol import ErrorMessage, Hello, Join, Joined, PoseUpdate, encode_update
from posecast.server.actions import INFO, Hold, Log
from posecast.server.auth import make_token
from posecast.server.core import Close, RelayCore, ServerConfig
from posecast.server.limits import normalise_room

NAN_POSE = np.array([[float("nan"), 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]])


def closes(actions: list[object]) -> list[Close]:
    return [a for a in actions if isinstance(a, Close)]


def errors_of(c: Client, now: float) -> list[ErrorMessage]:
    return [e for e in c.read(now) if isinstance(e, ErrorMessage)]


def stored_capture(core: RelayCore, room: str = "lobby") -> list[float]:
    return sorted(s.capture for s in core.rooms[room]._streams.values())


# -- 1. capture times against the server clock ------------------------------------------


@pytest.mark.parametrize(
    ("offset", "kind"),
    [(-2.0, "stale-capture"), (-1.01, "stale-capture"), (0.3, "future-capture")],
)
def test_an_update_captured_out_of_the_window_is_refused(offset: float, kind: str) -> None:
    """Not stored nor relayed; counted; a drops record; a non-fatal bad-pose error."""
    core = RelayCore(ServerConfig(record_dir=Path("unused")))
    core.add_room("lobby", True, 0.0)
    a = connect(core, 10.0)
    a.publish(10.0)
    actions = a.publish(10.5, capture=10.5 + offset)
    assert closes(actions) == []
    assert stored_capture(core) == [10.0] * 3  # the honest keyframe stays
    (err,) = errors_of(a, 10.5)
    assert (err.code, err.fatal, err.in_reply_to) == ("bad-pose", False, "update")
    stats = core.peer(a.conn).statistics()
    counted = {"stale-capture": stats.stale_captures, "future-capture": stats.future_captures}
    assert counted[kind] == 1 and sum(counted.values()) == 1
    room = core.rooms["lobby"]
    room.flush_drops(12.0, force=True)
    assert {"kind": kind, "user": a.user, "count": 1} in recorded(core.pending(), "drop")


@pytest.mark.parametrize("offset", [-0.99, 0.0, 0.24])
def test_an_update_inside_the_window_is_kept(offset: float) -> None:
    core = RelayCore()
    a = connect(core, 10.0)
    a.publish(10.0, capture=10.0 + offset)
    assert stored_capture(core) == pytest.approx([10.0 + offset] * 3, abs=1e-6)
    assert errors_of(a, 10.0) == []


def test_capture_window_is_configurable() -> None:
    core = RelayCore(ServerConfig(max_capture_age=5.0, max_capture_ahead=0.0))
    a = connect(core, 10.0)
    a.publish(10.0, capture=6.0)
    a.publish(10.0, capture=10.01)
    assert stored_capture(core) == [6.0] * 3
    assert core.peer(a.conn).statistics().future_captures == 1


def test_a_position_out_of_the_room_volume_is_refused() -> None:
    """Positions within the room volume (here the cube of room_extent): beyond it,
    bad-pose and counted."""
    core = RelayCore(ServerConfig(room_extent=10.0))
    a = connect(core, 1.0)
    far = POSE.copy()
    far[1, 2] = -10.5
    ids = list(a.streams.values())
    a.send(PoseUpdate.from_arrays(1, ids, np.full(3, 1.0), far), 1.0)
    assert stored_capture(core) == []
    (err,) = errors_of(a, 1.0)
    assert err.code == "bad-pose" and "z=-10.50 m outside" in err.message
    assert core.peer(a.conn).statistics().out_of_bounds == 1
    a.send(PoseUpdate.from_arrays(2, ids, np.full(3, 1.0), POSE), 1.0)
    assert stored_capture(core) == [1.0] * 3


# -- 2. the misbehaviour budget -----------------------------------------------------------


def nan_update(c: Client, now: float) -> list[object]:
    c.seq += 1
    data = encode_update(c.seq, [c.streams["head"]], np.full(1, now), NAN_POSE)
    return list(c.core.receive(c.conn, data, now))


def test_over_budget_a_connection_is_closed_1008() -> None:
    """20 invalid frames at once are answered; the 21st closes the connection."""
    core = RelayCore(ServerConfig(misbehaviour_burst=20, misbehaviour_refill=5.0))
    a, b = connect(core, 1.0), connect(core, 1.0)
    for _ in range(20):
        assert closes(nan_update(a, 2.0)) == []
    assert closes(nan_update(a, 2.0)) == [
        Close(a.conn, 1008, "misbehaving: too many invalid frames")
    ]
    assert core.misbehaviour_closes == 1 and core.peer(b.conn).close_request is None


def test_the_budget_refills_and_counts_refused_updates_and_joins() -> None:
    """5 tokens a second come back; refused updates and bad room names cost one too."""
    core = RelayCore(ServerConfig(misbehaviour_burst=4, misbehaviour_refill=5.0))
    a = connect(core, 1.0)
    for _ in range(4):
        assert closes(nan_update(a, 2.0)) == []
    assert closes(a.publish(3.0, capture=9.0)) == []  # 1 s later: 4 tokens again (cap)
    assert closes(nan_update(a, 3.0)) == []
    assert closes(nan_update(a, 3.0)) == []
    assert closes(nan_update(a, 3.0)) == []
    assert closes(a.publish(3.0, capture=9.0)) != []  # a future capture costs one
    c = Client(core, core.connect(1.0))
    c.send(Hello(agent="t"), 1.0)
    c.read(1.0)
    for _ in range(4):
        assert closes(c.send(Join(room="\u202elobby", streams=("head",), rate=10.0), 1.0)) == []
        assert [e.code for e in errors_of(c, 1.0)] == ["bad-room"]  # back to READY
    assert closes(c.send(Join(room=" ", streams=("head",), rate=10.0), 1.0)) != []


def test_stale_captures_are_refused_but_never_charged() -> None:
    """An overloaded relay makes honest updates stale: refused and counted, but a
    client is never closed for the relay's own lag."""
    core = RelayCore(ServerConfig(misbehaviour_burst=2, misbehaviour_refill=0.0))
    a = connect(core, 1.0)
    for i in range(50):
        assert closes(a.publish(10.0 + 0.01 * i, capture=5.0)) == []
    assert core.peer(a.conn).statistics().stale_captures == 50
    assert core.peer(a.conn).close_request is None


def test_no_budget_when_burst_is_zero() -> None:
    core = RelayCore(ServerConfig(misbehaviour_burst=0))
    a = connect(core, 1.0)
    for _ in range(500):
        assert closes(nan_update(a, 2.0)) == []
        assert len(errors_of(a, 2.0)) == 1  # (read: an unread queue would close too-slow)


# -- 3. limits -----------------------------------------------------------------------------


def test_a_connection_that_does_not_join_in_time_is_closed() -> None:
    """next_expiry says when; expire closes 1008 "no join"; joined ones are left alone."""
    core = RelayCore(ServerConfig(join_timeout=5.0))
    idle = Client(core, core.connect(1.0))
    idle.send(Hello(agent="t"), 1.0)
    joined = connect(core, 2.0)
    assert core.next_expiry() == 6.0
    assert core.expire(5.9) == []
    assert closes(core.expire(6.0)) == [Close(idle.conn, 1008, "no join within 5 s")]
    assert core.join_timeouts == 1
    assert core.next_expiry() is None and core.expire(100.0) == []
    assert core.peer(joined.conn).close_request is None


def test_a_refused_join_does_not_stop_the_deadline() -> None:
    core = RelayCore(ServerConfig(join_timeout=5.0, max_members=1))
    connect(core, 1.0)
    late = connect(core, 1.0)
    assert core.peer(late.conn).room is None  # room-full
    assert [c.conn for c in closes(core.expire(6.0))] == [late.conn]


def test_connections_are_limited_in_total_and_per_address() -> None:
    """Over a limit: closed at once with 1013; an ended connection frees its place."""
    core = RelayCore(ServerConfig(max_connections=3, max_connections_per_address=2))
    a1 = core.connect(1.0, address="10.0.0.1")
    a2 = core.connect(1.0, address="10.0.0.1")
    assert core.pending() == []
    a3 = core.connect(1.0, address="10.0.0.1")
    why = "too many connections from one address (2)"
    assert core.pending() == [
        Log(INFO, "connection from %s refused: %s", ("10.0.0.1", why)),  # (the adapter logs it)
        Close(a3, 1013, f"try again later: {why}"),
    ]
    b1 = core.connect(1.0, address="10.0.0.2")
    assert core.pending() == []
    b2 = core.connect(1.0, address="10.0.0.2")
    assert closes(core.pending()) == [Close(b2, 1013, "try again later: too many connections (3)")]
    # Refused ones have no join deadline (they are closing already).
    assert {c.conn for c in closes(core.expire(10.0))} == {a1, a2, b1}
    for conn in (a3, b2, a1):
        core.disconnect(conn, 2.0)
    core.connect(2.0, address="10.0.0.1")
    assert core.pending() == [] and core.refused_connections == 2
    assert core.admission.by_address == {"10.0.0.1": 2, "10.0.0.2": 1}


def test_rooms_and_members_are_limited() -> None:
    """Over max_rooms or max_members: room-full, non-fatal; the client may join elsewhere."""
    core = RelayCore(ServerConfig(max_rooms=1, max_members=2))
    connect(core, 1.0, room="a")
    connect(core, 1.0, room="a")
    third = connect(core, 1.0, room="a")
    (err,) = [e for e in third.inbox if isinstance(e, ErrorMessage)]
    assert (err.code, err.fatal, err.in_reply_to) == ("room-full", False, "join")
    other = connect(core, 1.0, room="b")
    (err,) = [e for e in other.inbox if isinstance(e, ErrorMessage)]
    assert err.code == "room-full" and "too many rooms" in err.message
    assert set(core.rooms) == {"a"} and len(core.rooms["a"].members) == 2


def test_recorded_rooms_are_limited(tmp_path: Path) -> None:
    """A recording server opens no recorder beyond max_recorded_rooms: the join is refused."""
    core = RelayCore(ServerConfig(record_dir=tmp_path, max_recorded_rooms=1))
    first = Join(room="a", streams=("head",), rate=10.0)
    assert core.room_to_open(0, first, 0.0) == "a"
    assert core.add_room("a", True, 1.0)
    second = Join(room="b", streams=("head",), rate=10.0)
    assert core.room_to_open(0, second, 0.0) is None
    assert not core.add_room("b", True, 1.0)
    c = connect(core, 1.0, room="b")
    (err,) = [e for e in c.inbox if isinstance(e, ErrorMessage)]
    assert err.code == "room-full" and "recorded rooms" in err.message
    assert set(core.rooms) == {"a"}


class Cluster:
    """A cluster node that owns the rooms it is told (the core asks only must_claim)."""

    def __init__(self, owned: set[str]) -> None:
        self.owned = owned

    def must_claim(self, room: str) -> bool:
        return room not in self.owned


def test_which_joins_and_hellos_wait_for_the_adapter(tmp_path: Path) -> None:
    """The core decides what waits: a join creating a recorded room waits for its
    recording, a join of a room this node does not own for a claim, a hello resuming
    a member not parked here for the cluster's lookup; a join the core refuses anyway
    (bad name, bad token) waits for nothing."""
    core = RelayCore(ServerConfig(record_dir=tmp_path, secret="s3"))
    token = make_token("s3", "a", "ann", ttl=100.0, now=0.0)
    join_a = Join(room=" a", streams=("head",), rate=10.0, token=token)
    assert core.hold(1, join_a, 50.0) == Hold(1, "open", "a")
    assert core.hold(1, join_a, 150.0) is None  # expired: refused by the core, not held
    assert core.hold(1, Join(room="", streams=("head",), rate=10.0), 50.0) is None
    assert core.add_room("a", True, 1.0)
    assert core.hold(1, join_a, 50.0) is None  # open already
    core.cluster = Cluster(owned={"a"})
    assert core.hold(1, join_a, 50.0) is None
    join_b = Join(
        room="b", streams=("head",), rate=10.0, token=make_token("s3", "b", "ann", 100.0, 0.0)
    )
    assert core.hold(2, join_b, 50.0) == Hold(2, "claim", "b")
    assert core.hold(3, Hello(agent="x", resume="tok3n"), 50.0) == Hold(3, "resume", token="tok3n")
    assert core.hold(3, Hello(agent="x"), 50.0) is None


def test_room_names_are_one_room_or_refused() -> None:
    """ "lobby", "lobby " and "lobby\\n" are one room; NFC makes two spellings of é one.

    (``joined`` echoes the name as the client asked for it: its session checks that.)
    """
    core = RelayCore()
    for name in ("lobby", "lobby ", "lobby\n", "\tlobby"):
        c = connect(core, 1.0, room=name)
        assert [e.room for e in c.inbox if isinstance(e, Joined)] == [name]
    connect(core, 1.0, room="caf\u00e9")
    connect(core, 1.0, room="cafe\u0301")
    assert core.rooms.keys() == {"lobby", "caf\u00e9"}
    assert len(core.rooms["lobby"].members) == 4


@pytest.mark.parametrize(
    "name",
    ["", " ", "\n", "lob\x00by", "lob\x1bby", "lob\x85by", "\u202eybbol", "a\u2066b", "x" * 65],
)
def test_bad_room_names_are_refused(name: str) -> None:
    core = RelayCore()
    c = connect(core, 1.0, room=name)
    (err,) = [e for e in c.inbox if isinstance(e, ErrorMessage)]
    assert (err.code, err.fatal, err.in_reply_to) == ("bad-room", False, "join")
    assert core.rooms == {}
    assert closes(c.send(Join(room="ok", streams=("head",), rate=10.0), 1.0)) == []
    assert "ok" in core.rooms


def test_room_name_size_counts_bytes() -> None:
    assert normalise_room("é" * 32) == "é" * 32
    with pytest.raises(ValueError, match="66 bytes"):
        normalise_room("é" * 33)


def _held_join(core: RelayCore, now: float, room: str = "a") -> tuple[Client, Join]:
    """A client whose join of a room still to open the adapter holds (as connection.py)."""
    c = Client(core, core.connect(now))
    c.send(Hello(agent="t"), now)
    c.read(now)  # welcome
    join = Join(room=room, streams=("head",), rate=10.0)
    (event,) = core.frame(c.conn, c.session.send(join), now)
    assert core.hold(c.conn, event, 0.0) == Hold(c.conn, "open", room)
    return c, join


def test_a_held_join_is_not_closed_as_unjoined(tmp_path: Path) -> None:
    """A join that came in time but waits for its room's recording to open (slow under
    load) is not closed "no join within 5 s" while held; once handled, it joins."""
    core = RelayCore(ServerConfig(record_dir=tmp_path, join_timeout=5.0))
    c, join = _held_join(core, 1.0)
    assert core.expire(6.0) == [] and core.expire(30.0) == []
    assert core.join_timeouts == 0
    assert core.add_room("a", True, 31.0)
    core.unhold(c.conn)
    core.handle(c.conn, join, 31.0)
    assert core.peer(c.conn).room is not None
    assert closes(core.expire(100.0)) == []


def test_a_held_join_refused_after_its_hold_still_has_a_deadline(tmp_path: Path) -> None:
    """The hold only postpones the deadline: a join refused once handled (room full)
    leaves the connection unjoined, and it is closed a join_timeout later at most."""
    core = RelayCore(ServerConfig(record_dir=tmp_path, join_timeout=5.0, max_members=1))
    c, join = _held_join(core, 1.0)
    assert core.add_room("a", True, 2.0)
    connect(core, 2.0, room="a")  # takes the one place
    assert core.expire(8.0) == []  # held past its deadline (6.0): looked at again at 13
    core.unhold(c.conn)
    core.handle(c.conn, join, 9.0)
    assert core.peer(c.conn).room is None  # room-full
    assert core.next_expiry() == 13.0 and closes(core.expire(12.9)) == []
    assert [x.conn for x in closes(core.expire(13.0))] == [c.conn]
    assert core.join_timeouts == 1
