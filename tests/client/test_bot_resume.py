"""A bot whose TCP connection is cut reconnects and resumes by itself, on a real relay.

Its peer never sees it leave: no peer_left, the same user and stream ids, its
poses again after the resume. How soon they are shown again is printed, not
asserted (the machine is shared).
"""

from __future__ import annotations

import asyncio

import numpy as np
from support import poll_until, running_server

from posecast.client.bot import Bot, BotConfig
from posecast.protocol import PeerLeft, PeerResumed, PeerStalled


def _shown(peer: Bot, bot: Bot) -> bool:
    """``peer`` has received keyframes of each of ``bot``'s three streams."""
    if bot.conn is None or bot.conn.welcome is None:
        return False
    user = bot.conn.user
    mine = [rs for (u, _sid), rs in peer.remote.items() if u == user]
    return len(mine) == 3 and all(len(rs.arrival_local) > 0 for rs in mine)


async def _session() -> tuple[Bot, Bot, list[type]]:
    async with running_server() as srv:
        url = f"ws://127.0.0.1:{srv.port}"
        cfgs = [
            BotConfig(url=url, room="r", rate=20, duration=6.0, methods=("soa",), name=n, seed=i)
            for i, n in enumerate(("cut", "peer"))
        ]
        cut, peer = (Bot(c, srv.clock) for c in cfgs)
        notices: list[type] = []

        def spy(ev: object, arrival: float, size: int) -> None:
            if isinstance(ev, PeerStalled | PeerResumed | PeerLeft):
                notices.append(type(ev))

        peer.listen(spy)
        async with asyncio.TaskGroup() as tg:
            tasks = [tg.create_task(cut.run()), tg.create_task(peer.run())]
            # Cut it once the peer shows its poses (all three streams): a live session.
            await poll_until(lambda: _shown(peer, cut), limit=30.0)
            assert cut.conn is not None
            first = cut.conn
            first.ws.transport.abort()  # the network drops it
        reports = [t.result() for t in tasks]
        assert all(r.ending.kind == "complete" for r in reports), [r.ending for r in reports]
        assert cut.conn is not first
    return cut, peer, notices


def test_a_cut_bot_resumes_as_the_same_user_and_its_peer_sees_it_again() -> None:
    cut, peer, notices = asyncio.run(_session())
    assert len(cut.resumed_at) == 1
    # Never peer_left for the cut; one may close the list when the bots' sessions end
    # (both stop at 6 s, and whichever stops first says goodbye).
    assert notices in ([PeerStalled, PeerResumed], [PeerStalled, PeerResumed, PeerLeft])
    mine = [rs for (user, _sid), rs in peer.remote.items() if user == cut.conn.user]  # type: ignore[union-attr]
    assert len(mine) == 3
    back = cut.resumed_at[0]
    later = [a for rs in mine for a in rs.arrival_local if a > back]
    assert later, "the peer never received the resumed bot's poses"
    print(f"\nshown again {1000 * (min(later) - back):.0f} ms after the bot rejoined")
    assert np.all([np.all(np.diff(rs.capture) > 0) for rs in mine])
