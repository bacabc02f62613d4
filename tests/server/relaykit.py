"""Helpers for the relay tests: well-behaved bots that publish, record and measure.

A :class:`Bot` wraps a real :class:`client.connection.ClientConnection`: it
publishes its own streams at a fixed rate (remembering every float32 pose and
capture time it sent) and records everything it receives with arrival times.
``keyframe_rates`` counts new keyframes per remote stream in a time window.
"""

from __future__ import annotations

import asyncio
import bisect
import contextlib
import itertools
import json
import os
import socket
import sys
from collections.abc import AsyncIterator, Awaitable, Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import msgpack
import numpy as np
from support import Pacer, poll_until
from websockets.asyncio.client import ClientConnection as WsConnection
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

from posecast.client.connection import ClientConnection
from posecast.protocol import (
    ErrorMessage,
    Ping,
    Pong,
    PoseUpdate,
    Snapshot,
    decode_message,
    encode_update,
)
from posecast.server.app import RelayServer
from posecast.server.room import Room

T = TypeVar("T")
Clock = Callable[[], float]
StreamKey = tuple[int, int]  # (user, stream)


async def settle(condition: Callable[[], bool], limit: float = 10.0) -> None:
    """Poll until ``condition()`` holds; ``limit`` seconds is a hang guard, not a timing check."""
    await poll_until(condition, limit=limit, every=0.01)


def random_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    """``n`` poses with unit quaternions, already float32 (what the wire carries)."""
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    p = rng.uniform(-2.0, 2.0, size=(n, 3))
    return np.concatenate([p, q], axis=1).astype(np.float32)


@dataclass
class Sent:
    """What a bot published on one stream: capture times (float64, as decoded) and poses."""

    captures: list[float] = field(default_factory=list)
    poses: list[np.ndarray] = field(default_factory=list)

    def find(self, capture: float, tol: float) -> np.ndarray | None:
        i = bisect.bisect_left(self.captures, capture - tol)
        if i < len(self.captures) and abs(self.captures[i] - capture) <= tol:
            return self.poses[i]
        return None


@dataclass
class Bot:
    """A joined client that publishes and records; run it with :meth:`running`."""

    conn: ClientConnection
    clock: Clock
    publish_rate: float = 30.0
    seed: int = 0
    snapshots: list[tuple[float, Snapshot]] = field(default_factory=list)
    others: list[object] = field(default_factory=list)
    sent: dict[int, Sent] = field(default_factory=dict)
    closed: ConnectionClosed | None = None

    @classmethod
    async def join(
        cls,
        url: str,
        clock: Clock,
        *,
        room: str,
        rate: float,
        streams: tuple[str, ...] = ("head", "left", "right"),
        publish_rate: float = 30.0,
        seed: int = 0,
    ) -> Bot:
        conn = await ClientConnection.open(url, room=room, streams=streams, rate=rate, clock=clock)
        bot = cls(conn, clock, publish_rate, seed)
        bot.others.extend(conn.early_peers)
        return bot

    @property
    def user(self) -> int:
        return self.conn.user

    @property
    def stream_ids(self) -> list[int]:
        assert self.conn.joined is not None
        return list(self.conn.joined.streams.values())

    async def _publish(self) -> None:
        rng = np.random.default_rng(self.seed)
        ids = self.stream_ids
        pacer = Pacer(1.0 / self.publish_rate, self.clock)
        seq = 0
        while True:
            now = self.clock()
            # Capture times a little apart per stream, so offsets are not all zero.
            captures = now - 0.001 * np.arange(len(ids))
            update = PoseUpdate.from_arrays(seq, ids, captures, random_poses(rng, len(ids)))
            for sid, cap, p in zip(ids, update.capture_times, update.poses, strict=True):
                s = self.sent.setdefault(sid, Sent())
                s.captures.append(float(cap))
                s.poses.append(np.array(p))
            await self.conn.send(update)
            seq = await pacer.next()

    async def _record(self) -> None:
        try:
            while True:
                rec = await self.conn.recv()
                if isinstance(rec.event, Snapshot):
                    self.snapshots.append((rec.arrival, rec.event))
                else:
                    self.others.append(rec.event)
        except ConnectionClosed as exc:
            self.closed = exc

    @contextlib.asynccontextmanager
    async def running(self, publish: bool = True) -> AsyncIterator[Bot]:
        """Publish (if asked) and record in the background while the block runs."""
        tasks = [asyncio.create_task(self._record())]
        if publish:
            tasks.append(asyncio.create_task(self._publish()))
        try:
            yield self
        finally:
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

    @property
    def rate(self) -> float:
        """The snapshot rate the server granted."""
        assert self.conn.joined is not None
        return self.conn.joined.rate

    def of_type(self, kind: type[T]) -> list[T]:
        """Everything but snapshots it received, of one message class, in order."""
        return [e for e in self.others if isinstance(e, kind)]


def keyframes_since(bot: Bot, t0: float) -> dict[StreamKey, int]:
    """New keyframes per remote stream among the snapshots ``bot`` got from ``t0`` on."""
    newest: dict[StreamKey, float] = {}
    counts: dict[StreamKey, int] = {}
    for arrival, snap in bot.snapshots:
        users, streams = snap.users.tolist(), snap.streams.tolist()
        caps = snap.capture_times.tolist()
        for key, cap in zip(zip(users, streams, strict=True), caps, strict=True):
            if cap > newest.get(key, -np.inf):
                newest[key] = cap
                if arrival >= t0:
                    counts[key] = counts.get(key, 0) + 1
    return counts


def window_full(bots: list[Bot], t0: float, seconds: float) -> bool:
    """Every bot got at least ``seconds`` of its granted rate in new keyframes of each
    other bot's streams since ``t0``."""
    for bot in bots:
        got = keyframes_since(bot, t0)
        need = seconds * bot.rate
        remote = [(b.user, s) for b in bots if b is not bot for s in b.stream_ids]
        if any(got.get(key, 0) < need for key in remote):
            return False
    return True


async def keyframe_window(
    bots: list[Bot], seconds: float, clock: Clock, limit: float = 60.0
) -> tuple[float, float]:
    """A window [t0, t1) of ``clock`` in which :func:`window_full` came to hold: waited
    for (polled), so a starved machine makes it longer, never short of keyframes."""
    t0 = clock()
    await poll_until(lambda: window_full(bots, t0, seconds), limit=limit, every=0.1)
    return t0, clock()


async def flowing(
    bots: list[Bot], publishers: list[Bot] | None = None, limit: float = 60.0
) -> None:
    """Wait until every bot has had a keyframe of each stream of the ``publishers``
    (default: all the bots) but its own."""
    pubs = bots if publishers is None else publishers

    def seen_all(bot: Bot) -> bool:
        seen = {
            (u, s)
            for _, snap in bot.snapshots
            for u, s in zip(snap.users.tolist(), snap.streams.tolist(), strict=True)
        }
        return all((b.user, s) in seen for b in pubs if b is not bot for s in b.stream_ids)

    await poll_until(lambda: all(seen_all(bot) for bot in bots), limit=limit, every=0.05)


async def barrier(bot: Bot) -> None:
    """A ping round trip on ``bot``'s connection: every reliable message the relay queued
    for it before it read the ping has arrived once the pong has (one ordered queue)."""
    seq = next(_PINGS)
    await bot.conn.send(Ping(seq=seq, time=bot.clock()))
    await settle(lambda: any(isinstance(e, Pong) and e.seq == seq for e in bot.others))


_PINGS = itertools.count(1_000_000)


def keyframe_rates(
    snapshots: Iterable[tuple[float, Snapshot]], t0: float, t1: float
) -> dict[StreamKey, float]:
    """New keyframes per second of each remote stream among snapshots arriving in [t0, t1)."""
    newest: dict[StreamKey, float] = {}
    counts: dict[StreamKey, int] = {}
    for arrival, snap in snapshots:
        caps = snap.capture_times
        users, streams = snap.users.tolist(), snap.streams.tolist()
        for user, stream, cap in zip(users, streams, caps.tolist(), strict=True):
            key = (user, stream)
            if cap > newest.get(key, -np.inf):
                newest[key] = cap
                if t0 <= arrival < t1:
                    counts[key] = counts.get(key, 0) + 1
    return {key: n / (t1 - t0) for key, n in counts.items()}


class DueTicks:
    """The relay's due ticks of some members of ``room``, as it runs them: each member's
    snapshot slots the relay reached (``Room.tick``'s own test of ``next_due``), with
    the server clock at that tick. A loaded machine makes the relay miss slots (it
    skips grid points it is late for): counting the slots it did reach, not seconds,
    keeps a rate check about the relay, not about the machine."""

    def __init__(self, room: Room, users: Iterable[int]) -> None:
        self.at: dict[int, list[float]] = {user: [] for user in users}
        tick = room.tick

        def spy(now: float, out: list[Any] | None = None) -> int:
            for user, times in self.at.items():
                member = room.members.get(user)
                if member is not None and not member.parked and member.next_due <= now + 1e-9:
                    times.append(now)
            return tick(now, out)

        room.tick = spy  # type: ignore[method-assign]

    def between(self, user: int, t0: float, t1: float) -> int:
        return sum(t0 <= t < t1 for t in self.at[user])


def keyframes_per_tick(bot: Bot, due: DueTicks, t0: float, t1: float) -> dict[StreamKey, float]:
    """New keyframes of each remote stream in the snapshots the relay built for ``bot``
    in [t0, t1) of the server clock, per due tick of ``bot`` in that span: 1.0 when every
    slot carries a new keyframe (publishers faster than the granted rate)."""
    newest: dict[StreamKey, float] = {}
    counts: dict[StreamKey, int] = {}
    for _, snap in bot.snapshots:
        inside = t0 <= snap.send_time < t1
        users, streams = snap.users.tolist(), snap.streams.tolist()
        for user, stream, cap in zip(users, streams, snap.capture_times.tolist(), strict=True):
            key = (user, stream)
            if cap > newest.get(key, -np.inf):
                newest[key] = cap
                if inside:
                    counts[key] = counts.get(key, 0) + 1
    n = due.between(bot.user, t0, t1)
    return {key: k / n for key, k in counts.items()} if n else {}


def rate_of(rates: dict[StreamKey, float], streams: Iterable[StreamKey]) -> float:
    """Mean keyframe rate over ``streams`` (0 for a stream never received)."""
    keys = list(streams)
    return sum(rates.get(k, 0.0) for k in keys) / len(keys)


# -- raw websocket clients, for hostile bytes ----------------------------------------


def frame(type_: str, **fields: object) -> bytes:
    """One msgpack map, valid or not."""
    data: bytes = msgpack.packb({"type": type_, **fields})
    return data


HELLO = frame("hello", version=1, agent="hostile")
GOOD = np.array([[0.5, 1.5, 0.0, 1.0, 0.0, 0.0, 0.0]], dtype=np.float32)


def join_frame(room: str, streams: tuple[str, ...] = ("head",), rate: float = 10.0) -> bytes:
    return frame("join", room=room, streams=list(streams), rate=rate)


async def raw_connect(url: str) -> WsConnection:
    """A plain websocket client, no posecast session: for hostile bytes."""
    return await connect(url, open_timeout=10, compression=None, max_size=2**20)


async def raw_join(
    ws: WsConnection, room: str, streams: tuple[str, ...] = ("head",)
) -> tuple[int, dict[str, int]]:
    """hello + join over a raw websocket; returns the user id and its stream ids by name."""
    await ws.send(HELLO)
    welcome = msgpack.unpackb(await ws.recv())
    assert welcome["type"] == "welcome", welcome
    await ws.send(join_frame(room, streams))
    while True:
        msg = msgpack.unpackb(await ws.recv())
        if msg["type"] == "joined":
            return int(welcome["user"]), dict(msg["streams"])
        assert msg["type"] in ("peer_joined", "snapshot"), msg


async def until_closed(ws: WsConnection, limit: float = 10.0) -> tuple[list[object], int | None]:
    """Read until the server closes: every decoded message, then the close code.

    ``limit`` seconds is a hang guard; the code is None if the server never closed.
    """
    got: list[object] = []
    try:
        async with asyncio.timeout(limit):
            while True:
                data = await ws.recv()
                raw = data.encode() if isinstance(data, str) else data
                got.append(decode_message(raw))
    except ConnectionClosed:
        pass
    rcvd = ws.protocol.close_rcvd
    return got, (rcvd.code if rcvd is not None else None)


def close_reason(ws: WsConnection) -> str | None:
    """The reason in the close frame the server sent, if any."""
    rcvd = ws.protocol.close_rcvd
    return rcvd.reason if rcvd is not None else None


def errors(messages: Iterable[object]) -> list[ErrorMessage]:
    return [m for m in messages if isinstance(m, ErrorMessage)]


async def never_reader(srv: RelayServer, room: str) -> tuple[WsConnection, int]:
    """A client that joins at 30 Hz and then stops reading its socket.

    Small socket buffers on both ends stand in for a slow link, so the server's
    writes back up within a second instead of after megabytes.
    """
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.setblocking(False)
    await asyncio.get_running_loop().sock_connect(sock, ("127.0.0.1", srv.port))
    ws = await connect(
        f"ws://127.0.0.1:{srv.port}",
        sock=sock,
        max_queue=1,
        compression=None,
        open_timeout=10,
        max_size=2**20,
    )
    await ws.send(HELLO)
    user = msgpack.unpackb(await ws.recv())["user"]
    await ws.send(join_frame(room, ("head",), rate=30.0))
    server_sock = srv.connection_of(user).ws.transport.get_extra_info("socket")
    server_sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
    return ws, user  # from here on nobody calls ws.recv()


async def joined_raw(url: str, room: str = "r") -> tuple[WsConnection, int, list[int]]:
    """A raw websocket joined to ``room`` with streams head and left: (ws, user, ids)."""
    ws = await raw_connect(url)
    user, streams = await raw_join(ws, room, ("head", "left"))
    return ws, user, list(streams.values())


def update_bytes(
    streams: list[int], poses: np.ndarray | list[list[float]], seq: int = 0, now: float = 0.0
) -> bytes:
    """An update frame, unchecked (any stream id, any pose values)."""
    return encode_update(seq, streams, np.full(len(streams), now), np.asarray(poses))


# -- attacks on a joined raw websocket: (attack, error code or None, close code) -----------


async def garbage(ws: WsConnection) -> None:
    await ws.send(b"\xc1\xc1 this is not msgpack")


async def text_frame(ws: WsConnection) -> None:
    await ws.send('{"type": "update"}')


async def truncated(ws: WsConnection) -> None:
    await ws.send(update_bytes([0], GOOD)[:-9])


async def oversize(ws: WsConnection) -> None:
    await ws.send(frame("event", kind="button", payload="x" * 70_000))


async def unknown_type(ws: WsConnection) -> None:
    await ws.send(frame("teleport", to="mars"))


async def join_twice(ws: WsConnection) -> None:
    await ws.send(join_frame("r"))


async def fatal_error_from_client(ws: WsConnection) -> None:
    await ws.send(frame("error", code="internal-error", message="client gave up", fatal=True))


Attack = Callable[[WsConnection], Awaitable[None]]

FATAL: dict[str, tuple[Attack, str | None, int]] = {
    "garbage bytes": (garbage, "bad-frame", 1002),
    "text frame": (text_frame, "bad-frame", 1002),
    "truncated msgpack": (truncated, "bad-frame", 1002),
    "oversize frame": (oversize, None, 1009),
    "unknown type": (unknown_type, "unknown-type", 1002),
    "join twice": (join_twice, "unexpected-message", 1002),
    "fatal error from client": (fatal_error_from_client, None, 1000),
}

#: Close code each attack of ``attack_rounds`` must get (None: it vanishes first).
EXPECTED_CLOSE: dict[str, int | None] = {
    **{name: close for name, (_, _, close) in FATAL.items()},
    "spoof": 1008,
    "before hello": 1002,
    "bad pose": None,
    "flood": None,
}


async def attack_rounds(url: str, room: str, victim: int, seconds: float) -> list[list[object]]:
    """Attack ``room`` until stdin closes, in at least two rounds of each attack
    (``seconds`` is a hang guard): [name, close code] of each attack, in order.

    Each round: one fatal attack (cycling through FATAL), a spoof of stream
    ``victim``, NaN and off-unit poses, a burst of updates beyond the rate limit
    and a join before hello. The last two vanish without a closing handshake.
    """
    loop = asyncio.get_running_loop()
    end = loop.time() + seconds
    stop = asyncio.Event()
    loop.add_reader(sys.stdin.fileno(), stop.set)  # readable: EOF, the test is done
    log: list[list[object]] = []
    kinds = list(FATAL.items())
    bad = [[float("nan"), 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.1, 0.0, 0.0, 0.0]]
    i = 0
    while (i < 2 * len(kinds) or not stop.is_set()) and loop.time() < end:
        name, (attack, _, _) = kinds[i % len(kinds)]
        i += 1
        ws, _, ids = await joined_raw(url, room)
        await attack(ws)
        log.append([name, (await until_closed(ws))[1]])
        ws, _, ids = await joined_raw(url, room)
        await ws.send(update_bytes([victim], GOOD))
        log.append(["spoof", (await until_closed(ws))[1]])
        ws, _, ids = await joined_raw(url, room)
        for seq in range(4):
            await ws.send(update_bytes(ids, bad, seq))
        ws.transport.abort()
        log.append(["bad pose", None])
        ws, _, ids = await joined_raw(url, room)
        with contextlib.suppress(ConnectionClosed):
            for seq in range(250):  # the bucket holds 120: the rest is dropped
                await ws.send(update_bytes(ids, [GOOD[0]] * 2, seq))
        ws.transport.abort()
        log.append(["flood", None])
        ws = await raw_connect(url)
        await ws.send(join_frame(room))
        log.append(["before hello", (await until_closed(ws))[1]])
    return log


def main(argv: list[str]) -> None:
    """``python relaykit.py URL ROOM VICTIM SECONDS``: attack until stdin closes (at most
    SECONDS), then print the log as JSON.

    Attackers are other programs in real life; running them in their own
    process keeps their CPU out of the server's event loop under test.
    """
    url, room, victim, seconds = argv
    # On a 2-core test machine an attacker at equal priority takes CPU from the
    # server process itself, which measures the OS scheduler, not the relay's
    # isolation of clients. Real attackers run elsewhere; yield the CPU.
    os.nice(10)
    print("attacking", flush=True)
    log = asyncio.run(attack_rounds(url, room, int(victim), float(seconds)))
    print(json.dumps(log), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
