"""The relay core's admission-and-membership part (``server.joins.Joins``) and its token
part (``server.tokens.Tokens``) keep their own state and answer through their public
methods: driven through a real core with protocol bytes and fake times."""

from __future__ import annotations

from test_core import Client, connect
from test_core_tokens import SECRET, WALL, joined, token

from posecast.protocol import Hello, Join, Renew
from posecast.server.core import RelayCore, ServerConfig
from posecast.server.joins import Joins
from posecast.server.tokens import Tokens


def test_the_join_deadlines_and_spectators_live_in_joins() -> None:
    """Admission sets a join deadline in Joins; a join ends it; a spectator is Joins'
    until it leaves."""
    core = RelayCore(ServerConfig(join_timeout=5.0))
    assert isinstance(core.joins, Joins)
    idle = Client(core, core.connect(1.0))
    assert core.joins.next_deadline() == 6.0
    member = connect(core, 2.0)
    viewer = Client(core, core.connect(3.0))
    viewer.send(Hello(agent="viewer"), 3.0)
    viewer.read(3.0)
    viewer.send(Join(room="lobby", streams=("head",), rate=10.0, spectator=True), 3.0)
    user = core.peer(viewer.conn).user
    assert core.joins.spectators == {user} and core.joins.is_spectator(user)
    assert not core.joins.is_spectator(core.peer(member.conn).user)
    assert core.joins.unjoined(5.9) == []
    assert core.joins.unjoined(6.0) == [idle.conn]  # the joined two are not due
    assert core.joins.next_deadline() is None
    core.disconnect(viewer.conn, 7.0)
    assert core.joins.spectators == set() and not core.is_spectator(user)


def test_the_token_deadlines_and_expiries_live_in_tokens() -> None:
    """A token's expiry is a deadline of Tokens, a renew moves it, an expiry is counted
    there (the core's ``token_expiries`` reads it)."""
    core = RelayCore(ServerConfig(secret=SECRET, join_timeout=0))
    assert isinstance(core.tokens, Tokens)
    alice, _ = joined(core, "alice", 1.0, ttl=30.0)
    alice.read(1.0)  # its session takes the joined
    assert core.tokens.next_deadline() == 31.0
    alice.send(Renew(token=token("alice", 60.0, 20.0)), 20.0, wall=20.0 + WALL)
    assert core.tokens.next_deadline() == 80.0
    assert core.tokens.expiries == 0
    core.expire(80.0)
    assert core.tokens.expiries == core.token_expiries == 1
    assert core.tokens.next_deadline() is None
