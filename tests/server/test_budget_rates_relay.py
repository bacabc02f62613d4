"""View-aware rates on a real relay: a subscriber that joins with ``budget_deg`` gets a
far still peer less often than a near moving one, each entry with its peer's own
capture time; /metrics shows the chosen rates; ``--no-view-rates`` ignores budgets."""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest
from support import Pacer, poll_until, running_server

from posecast.client.connection import ClientConnection
from posecast.client.core import ClientCore
from posecast.protocol import Join, PoseUpdate, Snapshot, encode_message
from posecast.protocol.errors import LocalProtocolError
from posecast.server.app import RelayServer, ServerConfig
from posecast.server.http import metrics_text

STREAMS = ("head", "left", "right")


def _poses(who: str, t: float) -> np.ndarray:
    """``near`` swings its hands 0.6 m in front of the subscriber; ``far`` stands still
    7 m away; ``me`` stands at the origin."""
    if who == "near":
        s = 0.3 * math.sin(2 * math.pi * 2.0 * t)
        rows = [(0.0, 1.6, -0.6), (-0.2 + s, 1.2, -0.5), (0.2 - s, 1.2, -0.5)]
    else:
        x = 7.0 if who == "far" else 0.0
        rows = [(x, 1.6, 0.0), (x - 0.2, 1.2, 0.0), (x + 0.2, 1.2, 0.0)]
    return np.array([[*r, 1.0, 0.0, 0.0, 0.0] for r in rows], np.float32)


async def _publish(
    conn: ClientConnection, srv: RelayServer, who: str, stop: asyncio.Event, sent: list[float]
) -> None:
    """``who``'s poses at 60 Hz until ``stop``; the capture times it sent go to ``sent``."""
    assert conn.joined is not None
    ids = np.array(list(conn.joined.streams.values()))
    pacer = Pacer(1 / 60)
    seq = 1
    while not stop.is_set():
        t = srv.clock()
        sent.append(t)
        await conn.send(PoseUpdate.from_arrays(seq, ids, np.full(3, t), _poses(who, t)))
        seq = await pacer.next() + 1


Sent = dict[int, list[float]]


async def _room(
    srv: RelayServer, codec: str, budget: float | None
) -> tuple[list[Snapshot], Sent, str]:
    """The subscriber (``me``, with ``budget``) and two publishers; until the subscriber
    has 90 snapshots. Returns its snapshots, each peer's sent capture times and the
    relay's /metrics text before anyone left."""
    url = f"ws://127.0.0.1:{srv.port}"
    me = await ClientConnection.open(url, room="v", streams=STREAMS, rate=30, codec=codec,
                                     budget_deg=budget)  # fmt: skip
    near = await ClientConnection.open(url, room="v", streams=STREAMS, rate=30, codec=codec)
    far = await ClientConnection.open(url, room="v", streams=STREAMS, rate=30, codec=codec)
    sent: dict[int, list[float]] = {}
    got: list[Snapshot] = []
    stop = asyncio.Event()

    async def receive() -> None:
        while True:
            ev = (await me.recv()).event
            if isinstance(ev, Snapshot):
                got.append(ev)

    async def drain(conn: ClientConnection) -> None:
        while True:
            await conn.recv()

    async with asyncio.TaskGroup() as tg:
        tasks = [tg.create_task(receive()), tg.create_task(drain(near)), tg.create_task(drain(far))]
        for conn, who in ((me, "me"), (near, "near"), (far, "far")):
            assert conn.welcome is not None
            times = sent.setdefault(conn.welcome.user, [])
            tasks.append(tg.create_task(_publish(conn, srv, who, stop, times)))
        await poll_until(lambda: len(got) >= 90, limit=60.0)
        stop.set()
        for t in tasks:
            t.cancel()
    text = metrics_text(srv.core, now=srv.clock())
    users = {who: c.welcome.user for who, c in (("near", near), ("far", far)) if c.welcome}
    for c in (me, near, far):
        await c.close()
    return got, {users["near"]: sent[users["near"]], users["far"]: sent[users["far"]]}, text


@pytest.mark.parametrize("codec", ["raw", "compact"])
async def test_a_far_still_peer_is_sent_less_often_than_a_near_moving_one(codec: str) -> None:
    """Budget 1 degree: the near peer is in most snapshots, the far one in few; every
    entry carries a capture time its peer really sent (per-peer times in one snapshot)."""
    async with running_server(ServerConfig(host="127.0.0.1", port=0)) as srv:
        snaps, sent, text = await _room(srv, codec, 1.0)
    near, far = sent
    tol = 1e-4 if codec == "raw" else 1.1e-3  # float32 offsets; compact: whole ms
    counts = {near: 0, far: 0}
    for snap in snaps[15:]:  # past the first updates, whose motion is not known yet
        for user in counts:
            counts[user] += user in {int(u) for u in snap.users}
        for u, t in zip(snap.users, snap.capture_times, strict=True):
            if int(u) in sent:
                assert min(abs(np.array(sent[int(u)]) - t)) < tol
    assert counts[near] > 2 * counts[far], counts
    assert counts[far] > 0, counts
    assert "posecast_view_rate_members 1" in text
    bucket5 = next(
        line for line in text.splitlines() if 'posecast_view_rate_hz_bucket{le="5"}' in line
    )
    assert int(bucket5.split()[-1]) > 0, bucket5


async def test_without_view_rates_a_budget_is_ignored() -> None:
    """``serve --no-view-rates``: a budget member gets both peers in (almost) every snapshot."""
    async with running_server(ServerConfig(host="127.0.0.1", port=0, view_rates=False)) as srv:
        snaps, sent, _ = await _room(srv, "raw", 1.0)
    far = list(sent)[1]
    assert sum(far in {int(u) for u in s.users} for s in snaps[15:]) >= 0.8 * len(snaps[15:])


def test_the_join_field_is_checked_and_absent_by_default() -> None:
    """budget_deg: in (0, 90) or a bad-message; a join without it is the bytes it was."""
    plain = Join(room="r", streams=("head",), rate=30.0)
    assert b"budget_deg" not in encode_message(plain)
    assert b"budget_deg" in encode_message(
        Join(room="r", streams=("head",), rate=30.0, budget_deg=1.5)
    )
    for bad in (0.0, -1.0, 90.0, float("nan"), "1"):
        with pytest.raises(LocalProtocolError, match="budget_deg"):
            Join(room="r", streams=("head",), rate=30.0, budget_deg=bad)  # type: ignore[arg-type]


def _far_stalls(snaps: list[Snapshot], far: int, per_peer: bool) -> tuple[int, float, float]:
    """The snapshots through a client core (arriving 5 ms after they were sent), frames
    at 90 Hz: the far peer's stalled stream frames after the first second, its D and
    the room's at the end."""
    core = ClientCore(("soa",), 30.0, per_peer=per_peer)
    start = snaps[0].send_time + 1.0
    frame, stalls = snaps[0].send_time, 0
    for snap in snaps:
        core.snapshot(snap, snap.send_time + 0.005)
        while frame <= snap.send_time + 0.005:
            out = core.render(core.playout(frame))
            if frame > start:
                rows = zip(core.shown(), out.frame.stalled.tolist(), strict=True)
                stalls += sum(s for k, s in rows if k[0] == far)
            frame += 1 / 90
    return stalls, core.delay.delay(far), core.delay.room.value


async def test_a_client_with_per_peer_delays_bridges_the_far_peer() -> None:
    """The relay's per-peer schedule through the client core: with per-peer delays the
    far peer (about 5 Hz) is shown later than the room's D and (almost) never stalls;
    with the room's D alone it stalls between its keyframes."""
    async with running_server(ServerConfig(host="127.0.0.1", port=0)) as srv:
        snaps, sent, _ = await _room(srv, "raw", 1.0)
    far = list(sent)[1]
    per_stalls, per_d, per_room = _far_stalls(snaps, far, per_peer=True)
    room_stalls, room_d, room_room = _far_stalls(snaps, far, per_peer=False)
    assert per_d > per_room + 2 / 30.0, (per_d, per_room)
    assert room_d == room_room
    assert room_stalls > 2 * max(per_stalls, 1), (per_stalls, room_stalls)
