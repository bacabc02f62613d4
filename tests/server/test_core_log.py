"""The relay core's log lines are actions (``Log``) its adapter writes: through a real
relay, each line still reaches the ``posecast.server`` logger, at its level.
"""

from __future__ import annotations

import logging

import pytest
from relaykit import joined_raw, raw_connect, settle, until_closed, update_bytes

from posecast.server.actions import ERROR, INFO, WARNING, Action, Log
from posecast.server.app import RelayServer, ServerConfig, serving
from posecast.server.core import RelayCore
from posecast.server.member import Member, Outbox
from posecast.server.room import Room


def _lines(caplog: pytest.LogCaptureFixture) -> list[tuple[str, int, str]]:
    return [(r.name, r.levelno, r.getMessage()) for r in caplog.records]


async def test_the_core_s_log_lines_reach_the_server_logger(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A room created and removed, a connection refused over the cap, a peer over its
    misbehaviour budget: one INFO line each on ``posecast.server``."""
    caplog.set_level(logging.INFO, logger="posecast.server")
    cfg = ServerConfig(
        host="127.0.0.1", port=0, max_connections=1, misbehaviour_burst=2, misbehaviour_refill=0.0
    )
    async with serving(RelayServer(cfg)) as srv:
        url = f"ws://127.0.0.1:{srv.port}"
        ws, user, ids = await joined_raw(url, "logged")
        extra = await raw_connect(url)  # over max_connections: closed 1013
        _, code = await until_closed(extra)
        assert code == 1013
        nan = [[float("nan"), 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]] * len(ids)
        for seq in range(3):  # bad-pose: refused, a token of the budget each
            await ws.send(update_bytes(ids, nan, seq, srv.clock()))
        _, code = await until_closed(ws)
        assert code == 1008
        await settle(lambda: not srv.rooms)
    lines = _lines(caplog)
    server = [(level, text) for name, level, text in lines if name == "posecast.server"]
    assert (INFO, "room 'logged' created") in server, lines
    assert (INFO, "room 'logged' removed") in server, lines
    assert (INFO, f"user {user}: over its misbehaviour budget, closing") in server, lines
    refused = [t for lv, t in server if lv == INFO and t.startswith("connection from 127.0.0.1")]
    assert refused == ["connection from 127.0.0.1 refused: too many connections (1)"], lines


def test_a_failed_room_tick_is_an_error_line_with_its_exception() -> None:
    """A room whose tick raises (a bug) is removed; the core returns the error line with
    the exception, whose traceback the adapter logs (``logging.exception`` as before)."""

    class Broken(Room):
        def tick(self, now: float, out: list[Action] | None = None) -> int:
            raise RuntimeError("boom")

    core = RelayCore(ServerConfig())
    broken = core.table.rooms["bad"] = Broken("bad", out=core.table.out)
    broken.add(Member(1, "u1", broken.allocate_streams(("head",)), 10.0, Outbox()), 9.0)
    core.table.rescheduled(broken)
    actions = core.tick(10.0)
    logs = [a for a in actions if isinstance(a, Log)]
    assert [(a.level, a.message % a.args) for a in logs] == [(ERROR, "room 'bad' failed")]
    assert isinstance(logs[0].error, RuntimeError) and "bad" not in core.rooms
    assert WARNING == logging.WARNING and INFO == logging.INFO and ERROR == logging.ERROR
