"""Bots that know several relays fail over when theirs dies, on real relays.

Two separate relays on loopback (``running_server``): bots given both URLs start
round-robin, and when relay A dies (every connection cut and the listener closed,
as a SIGKILL does) or goes away (1001), the bots on it carry on on relay B. B
does not hold their sessions, so they rejoin as new members: the same room,
streams and motion, new user ids. Their report says so; a bot that stayed on B
sees them join and scores them against their motion; a bot's scores of the peers
it knew on A stop at the rejoin. How long the failover took is printed, never
asserted (the machine is shared).
"""

from __future__ import annotations

import asyncio
import contextlib
import os
from dataclasses import replace

import pytest
from support import CliForker, poll_until, relayed, running_server

from posecast.client.bot import Bot, BotConfig, BotReport, run_bot
from posecast.client.connection import relay_urls
from posecast.client.remote import evaluate_remote
from posecast.client.swarm import reconnections, run_bots, swarm_report
from posecast.server.app import RelayServer, ServerConfig

#: Long enough that the failover happens well inside the session.
DURATION = 8.0


def _end(server: RelayServer, how: str) -> None:
    """``kill``: stop listening and cut every connection with no close frame (what a
    SIGKILL leaves behind); ``stop``: close each with 1001 "going away"."""
    server.stop()
    if how == "kill":
        for room in server.rooms.values():
            for user in list(room.members):
                server.connection_of(user).ws.transport.abort()


async def _failover(how: str) -> tuple[list[BotReport], str, str]:
    """Three bots given relays A and B (bots 0 and 2 start on A, bot 1 on B); once
    bots 0 and 2 exchange poses on A, A ends ``how``."""
    async with running_server() as a, running_server() as b:
        url_a, url_b = (f"ws://127.0.0.1:{s.port}" for s in (a, b))
        base = BotConfig(
            urls=(url_a, url_b),
            room="r",
            rate=20,
            duration=DURATION,
            methods=("soa",),
            motion="synthetic:orbit",
            keep_render_log=True,
        )
        async with asyncio.TaskGroup() as tg:
            swarm = tg.create_task(run_bots(base, 3))
            await poll_until(lambda: relayed(a, "r") >= 2 * 3 * 20)
            _end(a, how)
        return swarm.result(), url_a, url_b


@pytest.fixture(scope="module", params=["kill", "stop"])
def failover(request: pytest.FixtureRequest) -> tuple[list[BotReport], str, str]:
    return asyncio.run(_failover(request.param))


def test_bots_start_round_robin_and_the_ones_on_the_dead_relay_rejoin_the_other(
    failover: tuple[list[BotReport], str, str],
) -> None:
    """Bots 0 and 2 started on A, rejoined on B once each and ran their whole session."""
    reports, _url_a, url_b = failover
    assert [r.name for r in reports] == ["bot0", "bot1", "bot2"]
    assert all(r.ending.kind == "complete" for r in reports), [r.ending for r in reports]
    assert [(r.rejoined, r.resumed) for r in reports] == [(1, 0), (0, 0), (1, 0)]
    assert all(r.relay == url_b for r in reports)
    report = swarm_report(reports)
    assert report["reconnects"] == {
        "resumed": 0,
        "rejoined": 2,
        "lines": [
            f"reconnected after a drop: bot0 rejoined 1 (now on {url_b}); "
            f"bot2 rejoined 1 (now on {url_b})"
        ],
    }
    assert [(b["rejoined"], b["relay"]) for b in report["bots"]] == [
        (1, url_b),
        (0, url_b),
        (1, url_b),
    ]
    assert report["ending"]["exit_code"] == 0


def test_the_bot_that_stayed_sees_them_join_and_scores_them(
    failover: tuple[list[BotReport], str, str],
) -> None:
    """Bot 1 (on B) gets both rejoined bots' head and hands, labelled with their motion,
    and scores them: every class of both has samples."""
    reports, *_ = failover
    stayed = reports[1]
    others = {reports[0].user, reports[2].user}
    assert {rs.user for rs in stayed.streams.values()} == others
    assert sorted(rs.name for rs in stayed.streams.values()) == sorted(
        ["head", "left", "right"] * 2
    )
    assert all(
        rs.label and rs.label.startswith("synthetic:orbit") for rs in stayed.streams.values()
    )
    for classes in stayed.qoe.values():
        assert set(classes) == {"head", "hands"}
        assert all(s.samples > 0 for s in classes.values())


def test_a_rejoined_bot_scores_the_peers_it_left_until_it_left(
    failover: tuple[list[BotReport], str, str],
) -> None:
    """Bot 0 keeps bot 2's streams from A apart from those it got on B (bot 2's new id
    may equal its old one or bot 1's), and scores the old ones only until it rejoined:
    the hold after that is not counted as stalls."""
    reports, *_ = failover
    rep, peer = reports[0], reports[2]
    old = [rs for key, rs in rep.streams.items() if key[0] > 0xFFFF]
    new = [rs for key, rs in rep.streams.items() if key[0] <= 0xFFFF]
    assert sorted(rs.name for rs in old) == ["head", "left", "right"]
    assert {rs.user for rs in new} == {reports[1].user, peer.user}
    assert len(new) == 6
    # Same motion label before and after: the peer rejoined as what it plays.
    assert {rs.label for rs in old} == {rs.label for rs in new if rs.user == peer.user}
    pt = [f[0] for f in rep.render_log]
    pd = [f[1] for f in rep.render_log]
    to_the_end = evaluate_remote(rep.streams, pt, pd, ("soa",))["soa"]
    scored = rep.qoe["soa"]
    stalls = {cls: (scored[cls].stalls, to_the_end[cls].stalls) for cls in scored}
    print(f"\nstalls scored / if held to the end: {stalls}")
    for cls in scored:
        assert scored[cls].samples < to_the_end[cls].samples
        assert scored[cls].stalls < to_the_end[cls].stalls


async def _restart() -> list[Bot]:
    """Two bots with one URL; their relay dies and a new one starts on the same port."""
    async with contextlib.AsyncExitStack() as stack:
        first = await stack.enter_async_context(running_server())
        url = f"ws://127.0.0.1:{first.port}"
        bots = [
            Bot(
                BotConfig(url=url, room="r", rate=20, duration=DURATION, methods=("soa",), seed=i),
                first.clock,
            )
            for i in range(2)
        ]
        async with asyncio.TaskGroup() as tg:
            for bot in bots:
                tg.create_task(bot.run())
            await poll_until(lambda: relayed(first, "r") >= 2 * 3 * 20)
            _end(first, "kill")
            killed = first.clock()
            config = ServerConfig(host="127.0.0.1", port=first.port)
            again = await stack.enter_async_context(running_server(config))
            await poll_until(lambda: all(b.rejoined_at for b in bots))
            after = [round(1000 * (b.rejoined_at[0] - killed)) for b in bots]
            print(f"\nrejoined {after} ms after the kill")
            assert again.rooms["r"].members
    return bots


def test_one_url_bots_rejoin_a_relay_that_lost_their_sessions() -> None:
    """A relay restarted (its sessions gone) within the resume window: bots with one URL
    rejoin it as new members instead of ending as lost, and see each other again."""
    bots = asyncio.run(_restart())
    for bot, other in (bots, bots[::-1]):
        assert bot.ending is None, bot.ending
        assert (len(bot.rejoined_at), len(bot.resumed_at)) == (1, 0)
        assert bot.conn is not None and other.conn is not None
        back = bot.rejoined_at[0]
        later = [
            a
            for (user, _), rs in bot.remote.items()
            if user == other.conn.user
            for a in rs.arrival_local
            if a > back
        ]
        assert later, "no poses of the other bot after the rejoin"


def test_relay_urls_reads_a_comma_separated_list() -> None:
    """One URL is a list of one; spaces around items are dropped; order is kept."""
    assert relay_urls("ws://a:8765") == ("ws://a:8765",)
    assert relay_urls("ws://a:8765, wss://b:8765") == ("ws://a:8765", "wss://b:8765")


BAD_LISTS = [
    ("ws://a:8765,,ws://b:8765", "empty URL"),
    ("ws://a:8765,", "empty URL"),
    ("http://a:8765", "not a ws:// or wss:// URL"),
    ("ws://a:8765,b:8765", "not a ws:// or wss:// URL"),
    ("ws://:8765", "not a ws:// or wss:// URL"),
    ("ws://a:port", "not a valid URL"),
    ("ws://a:8765,ws://a:8765", "listed twice"),
]


@pytest.mark.parametrize(("text", "says"), BAD_LISTS)
def test_bad_url_lists_are_refused_with_the_reason(text: str, says: str) -> None:
    """relay_urls refuses an empty item, a URL that is not ws:// or wss:// with a host,
    a bad port, and a URL listed twice, saying which."""
    with pytest.raises(ValueError, match=says):
        relay_urls(text)


@pytest.mark.parametrize(("text", "says"), [BAD_LISTS[0], BAD_LISTS[3], BAD_LISTS[6]])
def test_bad_url_lists_are_one_line_cli_errors(text: str, says: str, cli: CliForker) -> None:
    """`posecast bots --url LIST` refuses a bad list before connecting: one line on
    stderr, exit code 2, no traceback."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("POSECAST_")}
    code, _, stderr = cli.run(["bots", "--url", text, "--duration", "1"], env, limit=120)
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert code == 2, stderr
    assert len(lines) == 1 and lines[0].startswith("error: --url: "), stderr
    assert says in lines[0]


def test_relays_put_the_start_url_first_and_keep_the_order() -> None:
    """BotConfig.relays: ``url`` first, then the ones after it in ``urls``, cycling."""
    assert BotConfig(url="ws://a").relays == ("ws://a",)
    assert BotConfig(urls=("ws://a", "ws://b", "ws://c")).relays == ("ws://a", "ws://b", "ws://c")
    cfg = BotConfig(url="ws://b", urls=("ws://a", "ws://b", "ws://c"))
    assert cfg.relays == ("ws://b", "ws://c", "ws://a")
    assert BotConfig(url="ws://x", urls=("ws://a",)).relays == ("ws://x", "ws://a")


def test_reconnection_lines_name_the_bots_that_moved(
    failover: tuple[list[BotReport], str, str],
) -> None:
    """No line when nobody reconnected; the swarm report's lines otherwise."""
    reports, *_ = failover
    assert reconnections([reports[1]]) == []
    assert len(reconnections(reports)) == 1


async def _all_go_away() -> list[BotReport]:
    """Two bots given relays A and B, both on A; then every relay shuts down (1001)."""
    async with running_server() as a, running_server() as b:
        urls = tuple(f"ws://127.0.0.1:{s.port}" for s in (a, b))
        cfgs = [
            BotConfig(urls=urls, room="r", duration=60.0, methods=("soa",), seed=i, name=f"b{i}")
            for i in range(2)
        ]
        async with asyncio.TaskGroup() as tg:
            tasks = [tg.create_task(run_bot(replace(c, resume_window=1.0))) for c in cfgs]
            await poll_until(lambda: relayed(a, "r") >= 2 * 3 * 20)
            b.stop()
            a.stop()
        return [t.result() for t in tasks]


def test_when_every_relay_goes_away_the_session_ends_closed_not_lost() -> None:
    """A 1001 with other relays to try sends the bot to them; when none answers within
    its window the session ends as the server closed it (graceful), not as lost."""
    for rep in asyncio.run(_all_go_away()):
        assert rep.ending.kind == "closed", rep.ending
        assert (rep.ending.code, rep.ending.reason) == (1001, "going away")
        assert rep.ending.graceful
        assert (rep.resumed, rep.rejoined) == (0, 0)
