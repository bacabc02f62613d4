"""Events over their connection's bucket are dropped before they are decoded (issue 29):
a real relay, a member flooding events, an honest member in the same room."""

from __future__ import annotations

import msgpack
from relaykit import Bot, barrier, frame, joined_raw, settle
from support import running_server

from posecast.protocol import ErrorMessage, UserEvent
from posecast.server.app import RelayServer, ServerConfig
from posecast.server.peer import Peer

RATE = 60.0


def url_of(srv: RelayServer) -> str:
    return f"ws://127.0.0.1:{srv.port}"


def peer_of(srv: RelayServer, user: int) -> Peer:
    return next(p for p in srv.core.peers.values() if p.user == user)


def decoded(peer: Peer) -> int:
    """Frames of ``peer`` its session decoded."""
    return peer.session.statistics().frames_received


async def test_flooded_events_dropped_undecoded_honest_member_unaffected() -> None:
    cfg = ServerConfig(host="127.0.0.1", port=0, max_update_rate=RATE)
    async with running_server(cfg) as srv:
        bot = await Bot.join(url_of(srv), srv.clock, room="r", rate=20.0, seed=11)
        async with bot.running():
            ws, user, ids = await joined_raw(url_of(srv), "r")
            peer = peer_of(srv, user)
            frames0, decoded0 = peer.frames_in, decoded(peer)
            start = srv.clock()
            # 300 events at once: one second's burst (60) passes, the rest is a flood
            # short of the close (10 s worth of drops), so every drop is one event.
            for k in range(300):
                await ws.send(frame("event", kind="button", stream=ids[0], payload={"k": k}))
            await settle(lambda: peer.frames_in - frames0 == 300)
            elapsed = srv.clock() - start
            dropped = peer.flood_drops
            assert 300 - RATE * (1.0 + elapsed) <= dropped < 300
            # Every dropped event was dropped before its decode; the others were decoded.
            assert decoded(peer) - decoded0 == 300 - dropped
            assert peer.close_request is None
            # The same flood with "type" not first: not recognised by the peek, decoded,
            # and still limited after the decode by the same bucket.
            drops0, decoded1 = peer.flood_drops, decoded(peer)
            for k in range(200):
                event = {"kind": "button", "stream": ids[0], "payload": {"k": k}, "type": "event"}
                await ws.send(msgpack.packb(event))
            await settle(lambda: peer.frames_in - frames0 == 500)
            assert decoded(peer) - decoded1 == 200
            assert peer.flood_drops - drops0 >= 200 - RATE * (1.0 + srv.clock() - start)
            # The honest member: events within the bucket only, no error, still served.
            await barrier(bot)
            events = bot.of_type(UserEvent)
            assert 0 < len(events) <= 500 - peer.flood_drops
            assert not bot.of_type(ErrorMessage)
            snapshots = len(bot.snapshots)
            await settle(lambda: len(bot.snapshots) > snapshots + 5)
            assert bot.closed is None
            # Refilled, the flooder's next event goes through as any other.
            await settle(lambda: peer.would_admit(RATE, srv.clock()))
            await ws.send(frame("event", kind="button", stream=ids[0], payload={"k": -1}))
            await settle(lambda: any(e.payload == {"k": -1} for e in bot.of_type(UserEvent)))
            await ws.close()
        await bot.conn.close()
