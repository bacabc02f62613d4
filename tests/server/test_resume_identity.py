"""A resume is bound to the session that was given its token (and to its token user).

A hello naming a parked member without its token's secret, or a resumed join with
another user's access token (or none), is refused (``unauthorized``, 1008) and the
parked member stays parked: its own client resumes afterwards as if nothing happened.
Sans-I/O first (time is an argument), then over real sockets.
"""

from __future__ import annotations

import asyncio

import msgpack
from support import running_server
from test_core import Client
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

from posecast.client.connection import ClientConnection
from posecast.protocol import (
    ErrorMessage,
    Hello,
    Join,
    Joined,
    PeerLeft,
    PeerResumed,
    Welcome,
    decode_message,
)
from posecast.server.actions import Close
from posecast.server.auth import make_token
from posecast.server.core import RelayCore, ServerConfig
from posecast.server.parking import ID_LENGTH

STREAMS = ("head", "left", "right")
SECRET = "s3cret"


def token(user: str, now: float) -> str:
    return make_token(SECRET, "lobby", user, ttl=600, now=now)


def hello(core: RelayCore, now: float, resume: str | None = None) -> tuple[Client, list[object]]:
    c = Client(core, core.connect(now))
    c.send(Hello(agent="r", resumable=True, resume=resume), now, wall=now)
    return c, c.read(now)


def join(c: Client, now: float, access: str | None = None) -> list[object]:
    c.send(Join(room="lobby", streams=STREAMS, rate=10.0, token=access), now, wall=now)
    return c.read(now)


def welcome_of(events: list[object]) -> Welcome:
    (welcome,) = [e for e in events if isinstance(e, Welcome)]
    return welcome


def refused(c: Client) -> bool:
    """``c`` got unauthorized and a 1008 close."""
    codes = [e.code for e in c.inbox if isinstance(e, ErrorMessage)]
    closes = [a.code for a in c.actions if isinstance(a, Close)]
    return codes == ["unauthorized"] and closes == [1008]


def parked_pair(core: RelayCore, secret: bool) -> tuple[str, int, Client]:
    """Member "alice" parked (her socket dropped) and a peer; (her token, her user, peer)."""
    a, got = hello(core, 1.0)
    join(a, 1.0, token("alice", 1.0) if secret else None)
    peer, _ = hello(core, 1.0)
    join(peer, 1.0, token("bob", 1.0) if secret else None)
    core.disconnect(a.conn, 2.0)  # dropped: parked
    welcome = welcome_of(got)
    assert welcome.resume is not None
    return welcome.resume, welcome.user, peer


def resumes(core: RelayCore, resume: str, user: int, now: float, secret: bool) -> None:
    """Alice's own client resumes: same user id, joined again."""
    back, got = hello(core, now, resume=resume)
    welcome = welcome_of(got)
    assert welcome.resumed and welcome.user == user
    events = join(back, now, token("alice", now) if secret else None)
    assert [e for e in events if isinstance(e, Joined)]
    assert core.parking.resumes == 1


def test_a_resume_token_with_the_wrong_secret_is_refused_and_disturbs_nothing() -> None:
    """Alice's token id with another secret: 1008, and alice still resumes."""
    core = RelayCore()
    resume, user, peer = parked_pair(core, secret=False)
    forged = resume[:ID_LENGTH] + ("A" if resume[-1] != "A" else "B") * (len(resume) - ID_LENGTH)
    thief, got = hello(core, 2.5, resume=forged)
    assert not [e for e in got if isinstance(e, Welcome)] and refused(thief)
    core.disconnect(thief.conn, 2.5)
    assert core.parking.refused == 1 and core.parking.has(resume)
    resumes(core, resume, user, 3.0, secret=False)
    assert not [e for e in peer.read(3.0) if isinstance(e, PeerLeft)]


def test_another_users_access_token_cannot_resume_a_parked_member() -> None:
    """Alice's whole resume token with mallory's access token: refused at join; alice
    resumes after."""
    core = RelayCore(ServerConfig(secret=SECRET))
    resume, user, peer = parked_pair(core, secret=True)
    thief, _ = hello(core, 2.5, resume=resume)
    events = join(thief, 2.5, token("mallory", 2.5))
    assert not [e for e in events if isinstance(e, Joined)] and refused(thief)
    core.disconnect(thief.conn, 2.5)
    assert core.parking.refused == 1
    resumes(core, resume, user, 3.0, secret=True)
    assert not [e for e in peer.read(3.0) if isinstance(e, PeerLeft)]


def test_a_resume_with_no_access_token_does_not_force_the_member_out() -> None:
    """A resumed hello whose join has no token, or that never joins: alice stays parked."""
    core = RelayCore(ServerConfig(secret=SECRET, join_timeout=1.0))
    resume, user, peer = parked_pair(core, secret=True)
    thief, _ = hello(core, 2.2, resume=resume)
    join(thief, 2.2, None)
    core.disconnect(thief.conn, 2.2)
    idle, _ = hello(core, 2.3, resume=resume)
    core.expire(3.3)  # it never joins: closed for that
    core.disconnect(idle.conn, 3.3)
    assert core.parking.has(resume)
    core.parking.resumes = 0  # (the two claims were given back)
    resumes(core, resume, user, 3.5, secret=True)
    assert [type(e) for e in peer.read(3.5) if isinstance(e, PeerLeft | PeerResumed)] == [
        PeerResumed
    ]


async def test_a_hijack_over_real_sockets_is_refused_and_the_owner_resumes() -> None:
    """Over loopback: a forged resume gets unauthorized and 1008; the dropped client
    then resumes with its own token, its peer never hears it left."""
    async with running_server(ServerConfig(host="127.0.0.1", port=0)) as srv:
        url = f"ws://127.0.0.1:{srv.port}"
        watcher = await ClientConnection.open(url, room="r", streams=STREAMS, rate=20)
        a = await ClientConnection.connect(url, resumable=True)
        assert a.welcome is not None and a.welcome.resume
        await a.join(room="r", streams=STREAMS, rate=20)
        a.ws.transport.abort()  # the network drops it
        resume = a.welcome.resume
        async with connect(url) as thief:
            forged = resume[:ID_LENGTH] + "x" * (len(resume) - ID_LENGTH)
            await thief.send(msgpack.packb({"type": "hello", "version": 1, "resume": forged}))
            got = [decode_message(await thief.recv())]
            try:
                async with asyncio.timeout(5):
                    while True:
                        got.append(decode_message(await thief.recv()))
            except ConnectionClosed:
                pass
            assert [e.code for e in got if isinstance(e, ErrorMessage)] == ["unauthorized"]
            assert thief.close_code == 1008
        b = await ClientConnection.connect(url, resume=resume)
        assert b.welcome is not None and b.welcome.resumed
        assert b.welcome.user == a.welcome.user
        await b.join(room="r", streams=STREAMS, rate=20)
        assert srv.core.parking.refused == 1
        await watcher.close()
        await b.close()
