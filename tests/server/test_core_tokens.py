"""Access tokens after the join: one live connection per (room, user), expiry, renew.

Sans-I/O like ``test_core.py``: the server clock and the wall clock are arguments.
The core's server clock runs at ``now``; the wall clock here is ``now + 1000``.
"""

from __future__ import annotations

from test_core import Client

from posecast.protocol import ErrorMessage, Hello, Join, Joined, Renew
from posecast.server.auth import make_token
from posecast.server.core import Close, Rearm, RelayCore, ServerConfig

SECRET = "s3cret"
WALL = 1000.0


def token(user: str, ttl: float, now: float, room: str = "lobby") -> str:
    return make_token(SECRET, room, user, ttl=ttl, now=now + WALL)


def joined(
    core: RelayCore, user: str, now: float, ttl: float = 60.0
) -> tuple[Client, list[object]]:
    c = Client(core, core.connect(now))
    c.send(Hello(), now)
    c.read(now)
    actions = c.send(
        Join(room="lobby", streams=("head",), rate=10.0, token=token(user, ttl, now)),
        now,
        wall=now + WALL,
    )
    return c, actions


def closes(actions: list[object]) -> list[tuple[int, str]]:
    return [(a.code, a.reason) for a in actions if isinstance(a, Close)]


def test_a_second_live_connection_of_one_user_is_refused() -> None:
    core = RelayCore(ServerConfig(secret=SECRET))
    alice, _ = joined(core, "alice", 1.0)
    assert any(isinstance(e, Joined) for e in alice.read(1.0))
    again, actions = joined(core, "alice", 2.0)
    assert closes(actions) == []  # refused, not closed: it may try again later
    (err,) = [e for e in again.read(2.0) if isinstance(e, ErrorMessage)]
    assert (err.code, err.in_reply_to, err.fatal) == ("user-taken", "join", False)
    assert len(core.rooms["lobby"].members) == 1
    # Another user joins fine; and once alice's first connection is gone, so does she.
    bob, _ = joined(core, "bob", 2.0)
    assert any(isinstance(e, Joined) for e in bob.read(2.0))
    core.disconnect(alice.conn, 3.0)
    back, _ = joined(core, "alice", 3.0)
    assert any(isinstance(e, Joined) for e in back.read(3.0))


def test_a_connection_is_closed_when_its_token_expires() -> None:
    core = RelayCore(ServerConfig(secret=SECRET, join_timeout=0))
    alice, actions = joined(core, "alice", 1.0, ttl=30.0)
    assert any(isinstance(a, Rearm) for a in actions)  # the adapter re-reads next_expiry
    assert core.next_expiry() == 31.0
    assert closes(core.expire(30.9)) == []
    assert closes(core.expire(31.0)) == [(1008, "access token expired")]
    errors = [e for e in alice.read(31.0) if isinstance(e, ErrorMessage)]
    assert [e.code for e in errors] == ["unauthorized"]
    assert core.token_expiries == 1


def test_renew_moves_the_deadline_and_a_bad_renew_closes() -> None:
    core = RelayCore(ServerConfig(secret=SECRET, join_timeout=0))
    alice, _ = joined(core, "alice", 1.0, ttl=30.0)
    alice.read(1.0)
    alice.send(Renew(token=token("alice", 60.0, 20.0)), 20.0, wall=20.0 + WALL)
    assert core.next_expiry() == 80.0
    assert closes(core.expire(31.0)) == []
    # A token of another user (or room) is refused: unauthorized, closed 1008.
    actions = alice.send(Renew(token=token("mallory", 60.0, 40.0)), 40.0, wall=40.0 + WALL)
    assert closes(actions) == [(1008, "access token is for user 'mallory', not 'alice'")]
    errors = [e for e in alice.read(40.0) if isinstance(e, ErrorMessage)]
    assert [(e.code, e.in_reply_to) for e in errors] == [("unauthorized", "renew")]


def test_an_open_server_ignores_renew_and_never_expires() -> None:
    core = RelayCore(ServerConfig(join_timeout=0))
    c = Client(core, core.connect(1.0))
    c.send(Hello(), 1.0)
    c.read(1.0)
    c.send(Join(room="lobby", streams=("head",), rate=10.0), 1.0)
    c.read(1.0)
    assert closes(c.send(Renew(token="anything"), 2.0)) == []
    assert core.next_expiry() is None
