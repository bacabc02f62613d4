"""The attacks of ``posecast bench hostile``, and what every attack shares.

The attacker process (:mod:`posecast.bench.hostile_attacker`) runs one of them. It
connects from its own loopback address (``127.0.0.2`` by default; the flood and
the room spam can take ``addresses`` of them in turn), so that the per-address
limits of the relay see it apart from the honest bots; prints
``{"event": "attacking"}`` once it is in place, attacks until its stdin closes,
its time bound passes or its count bound is reached, and prints
``{"event": "attack-result", ...}``: what it sent and what the server answered
(close codes and error codes, counted).

Attacks (the ones the relay was probed with in issue 14; those of issue 29 are in
:mod:`posecast.bench.hostile_room` and :mod:`posecast.bench.hostile_path`):

- ``timestamp``: a member publishing valid poses at 30 Hz stamped "now - 2 s";
- ``fuzz``: several joined connections sending a mix of invalid frames (NaN
  poses, truncated msgpack, random bytes, oversized frames, updates of streams
  they do not own), reconnecting whenever the server closes them;
- ``flood``: many websocket connections that never say hello nor join;
- ``never-reader``: a member that joins at 30 Hz and stops reading its socket;
- ``rooms``: connections that each join a room of their own name.
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import json
import socket
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import msgpack
import numpy as np
from websockets.asyncio.client import ClientConnection as WsConnection
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed, WebSocketException

from posecast.protocol import encode_update

__all__ = ["ATTACKS", "ATTACKS_14", "ATTACKS_29", "AttackConfig", "Tally", "signal"]

#: The attacks of issue 14, then those of issue 29, in the order the bench runs them.
ATTACKS_14 = ("timestamp", "fuzz", "flood", "never-reader", "rooms")
ATTACKS_29 = (
    "fuzz-in-room",
    "events-reconnect",
    "churn",
    "lag-liar",
    "slowloris",
    "resume-hijack",
    "blackhole",
)
ATTACKS = ATTACKS_14 + ATTACKS_29

#: A pose inside the default room volume (x, z in [-8, 8] m, y in [-2, 4] m).
_POSE = (0.5, 1.5, 0.0, 1.0, 0.0, 0.0, 0.0)
_OVERSIZE = 70_000


@dataclass
class AttackConfig:
    """One attack's target and bounds (the controller passes it as JSON)."""

    kind: str
    url: str
    room: str = "lobby"
    seconds: float = 20.0
    address: str = "127.0.0.2"
    addresses: int = 1
    fuzz_rate: float = 0.0
    stamp_age: float = 2.0
    fuzz_frames: int = 200_000
    fuzz_connections: int = 8
    flood_connections: int = 2000
    flood_rate: float = 250.0
    rooms: int = 300
    rooms_rate: float = 100.0
    seed: int = 0
    #: fuzz-in-room: members fuzzing in the honest room at once (each reconnects).
    room_fuzzers: int = 10
    #: events-reconnect: events a second, in all.
    event_rate: float = 10_000.0
    #: churn: joins (each then leaves) a second.
    churn_rate: float = 57.0
    #: slowloris: connections held at once, and opened (or reopened) a second at most.
    slowloris_connections: int = 3000
    slowloris_rate: float = 200.0
    #: resume-hijack: the relay's secret (a file: kept out of ``ps``), and attempts.
    secret_file: str | None = None
    hijack_attempts: int = 20
    #: blackhole: seconds after the first connection through the proxy opens that its
    #: path goes dead; < 0: when the controller signals ``cut``.
    blackhole_after: float = 3.0
    #: Wait for this signal from the controller before attacking (None: attack at once).
    wait_for: str | None = None


@dataclass
class Tally:
    """What an attack sent and what came back."""

    sent: Counter[str] = field(default_factory=Counter)
    closes: Counter[str] = field(default_factory=Counter)
    errors: Counter[str] = field(default_factory=Counter)
    extra: dict[str, Any] = field(default_factory=dict)

    def closed(self, ws: WsConnection | None) -> None:
        rcvd = None if ws is None else ws.protocol.close_rcvd
        code = "none" if rcvd is None else str(rcvd.code)
        if code == "1011":  # an internal error, or keepalive: the reason says which
            code += f" {rcvd.reason[:40]}" if rcvd is not None else ""
        self.closes[code] += 1

    def as_dict(self) -> dict[str, Any]:
        return {
            "sent": dict(self.sent),
            "closes": dict(self.closes),
            "errors": dict(self.errors),
            **self.extra,
        }


def _frame(type_: str, **fields: object) -> bytes:
    data: bytes = msgpack.packb({"type": type_, **fields})
    return data


_HELLO = _frame("hello", version=1, agent="bench-hostile")


def _address(cfg: AttackConfig, i: int) -> str:
    """Connection ``i``'s source address: ``cfg.addresses`` loopback addresses in turn."""
    return str(ipaddress.ip_address(cfg.address) + i % max(1, cfg.addresses))


async def _connect(
    cfg: AttackConfig, sock: socket.socket | None = None, i: int = 0
) -> WsConnection:
    """A plain websocket from the attacker's address (no posecast session yet)."""
    if sock is not None:
        return await connect(cfg.url, sock=sock, open_timeout=10, compression=None, max_queue=1)
    source = (_address(cfg, i), 0)
    return await connect(
        cfg.url, open_timeout=10, compression=None, local_addr=source, max_size=2**22
    )


async def _join(
    ws: WsConnection, room: str, streams: tuple[str, ...], rate: float, **join: object
) -> tuple[float, list[int]]:
    """hello + join (with the fields ``join``): (server clock minus ours, own stream ids);
    RuntimeError if refused."""
    await ws.send(_HELLO)
    welcome = msgpack.unpackb(await ws.recv())
    offset = float(welcome.get("server_time", time.monotonic())) - time.monotonic()
    await ws.send(_frame("join", room=room, streams=list(streams), rate=rate, **join))
    while True:
        msg = msgpack.unpackb(await ws.recv())
        if msg["type"] == "joined":
            return offset, [int(s) for s in msg["streams"].values()]
        if msg["type"] == "error":
            raise RuntimeError(str(msg.get("code")))


async def _count_replies(ws: WsConnection, tally: Tally) -> None:
    """Read everything the server sends, counting error codes, until it closes."""
    with contextlib.suppress(ConnectionClosed):
        async for data in ws:
            if isinstance(data, bytes) and b"error" in data[:40]:
                with contextlib.suppress(ValueError, msgpack.ExtraData, TypeError):
                    msg = msgpack.unpackb(data)
                    if isinstance(msg, dict) and msg.get("type") == "error":
                        tally.errors[str(msg.get("code"))] += 1


# -- the attacks -----------------------------------------------------------------------


async def _timestamp(cfg: AttackConfig, stop: asyncio.Event, tally: Tally) -> None:
    """A member publishing valid poses at 30 Hz, each stamped ``stamp_age`` s in the past
    (``timestamp``: refused as stale; ``lag-liar``: 30-300 ms, accepted but late)."""
    what = "stale-update" if cfg.kind == "timestamp" else "lagged-update"
    ws = await _connect(cfg)
    offset, ids = await _join(ws, cfg.room, ("head", "left", "right"), 30.0)
    ready()
    reader = asyncio.create_task(_count_replies(ws, tally))
    poses = np.tile(_POSE, (len(ids), 1))
    start, seq = time.monotonic(), 0
    try:
        while not stop.is_set() and not reader.done():
            stamp = time.monotonic() + offset - cfg.stamp_age
            poses[:, 0] = 0.5 + 0.2 * np.sin(stamp)
            await ws.send(encode_update(seq, ids, np.full(len(ids), stamp), poses))
            tally.sent[what] += 1
            seq += 1
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), max(0.0, start + seq / 30.0 - time.monotonic()))
    except ConnectionClosed:
        pass
    finally:
        await ws.close()
        await reader
        tally.closed(ws)


#: What each fuzzing connection sends all its life, in turn (NaN poses, which are
#: non-fatal and cost the misbehaviour budget, half the time; each other kind ends
#: the connection at its first frame, so the client writes on until it sees the close).
_FUZZ_KINDS = (
    "nan-pose",
    "truncated",
    "nan-pose",
    "random",
    "nan-pose",
    "oversize",
    "nan-pose",
    "not-owned",
)


def _fuzz_frames(kind: str, rng: np.random.Generator, ids: list[int], now: float) -> list[bytes]:
    """A batch of 16 frames of ``kind`` for a connection owning streams ``ids``."""
    n = len(ids)
    good = encode_update(0, ids, np.full(n, now), np.tile(_POSE, (n, 1)))
    if kind == "nan-pose":
        nan_pose = np.tile([np.nan, 1.5, 0.0, 1.0, 0.0, 0.0, 0.0], (n, 1))
        return [encode_update(k, ids, np.full(n, now), nan_pose) for k in range(16)]
    if kind == "truncated":
        return [good[: int(rng.integers(1, len(good)))] for _ in range(16)]
    if kind == "random":
        return [rng.bytes(int(rng.integers(1, 64))) for _ in range(16)]
    if kind == "oversize":
        return [_frame("event", kind="button", payload="x" * _OVERSIZE)] * 16
    stranger = [max(ids) + 1000 + int(rng.integers(1000))]
    return [encode_update(k, stranger, [now], [_POSE]) for k in range(16)]


async def _pace(cfg: AttackConfig, stop: asyncio.Event, sent: int, start: float) -> None:
    """With ``cfg.fuzz_rate``, wait until ``sent`` frames are due (spread over the run)."""
    if cfg.fuzz_rate > 0:
        ahead = start + sent / cfg.fuzz_rate - time.monotonic()
        if ahead > 0:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), ahead)


async def _fuzz_one(
    cfg: AttackConfig,
    stop: asyncio.Event,
    tally: Tally,
    rng: np.random.Generator,
    first: int,
    start: float,
) -> None:
    """One fuzzing connection after another until the frame budget or the time runs out."""
    turn = first
    while not stop.is_set() and sum(tally.sent.values()) < cfg.fuzz_frames:
        kind = _FUZZ_KINDS[turn % len(_FUZZ_KINDS)]
        turn += 1
        try:
            ws = await _connect(cfg)
            offset, ids = await _join(ws, cfg.room, ("head", "left"), 10.0)
        except (OSError, RuntimeError, WebSocketException, TimeoutError) as exc:
            tally.extra.setdefault("connect_failures", Counter())[type(exc).__name__] += 1
            await asyncio.sleep(0.05)
            continue
        reader = asyncio.create_task(_count_replies(ws, tally))
        batch = _fuzz_frames(kind, rng, ids, time.monotonic() + offset)
        try:
            while not stop.is_set() and sum(tally.sent.values()) < cfg.fuzz_frames:
                for data in batch:
                    await ws.send(data)
                tally.sent[kind] += len(batch)
                await asyncio.sleep(0)
                await _pace(cfg, stop, sum(tally.sent.values()), start)
        except ConnectionClosed:
            pass
        if ws.protocol.close_rcvd is not None:
            tally.closed(ws)
        else:  # out of time or frames before the server closed it: we close it
            tally.closes["closed by the attacker"] += 1
        if stop.is_set():
            ws.transport.abort()
        else:
            await ws.close()
        await reader


async def _fuzz(cfg: AttackConfig, stop: asyncio.Event, tally: Tally) -> None:
    """``fuzz_connections`` connections fuzzing at once, ``fuzz_frames`` frames in all.

    With ``fuzz_rate`` > 0 no faster than that many frames a second (the controller
    spreads them over the honest bots' run); otherwise as fast as it can.
    """
    ready()
    start = time.monotonic()
    async with asyncio.TaskGroup() as tg:
        for k in range(cfg.fuzz_connections):
            rng = np.random.default_rng(cfg.seed + k)
            tg.create_task(_fuzz_one(cfg, stop, tally, rng, k, start))


async def _hold(ws: WsConnection, stop: asyncio.Event, tally: Tally) -> None:
    """Keep a connection open, reading, until the server closes it or the attack ends."""
    reader = asyncio.create_task(_count_replies(ws, tally))
    stopped = asyncio.create_task(stop.wait())
    done, _ = await asyncio.wait([reader, stopped], return_when=asyncio.FIRST_COMPLETED)
    stopped.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await stopped
    if reader not in done:
        ws.transport.abort()
        await reader
        tally.closes["held to the end"] += 1
        return
    tally.closed(ws)


async def _open_paced(
    cfg: AttackConfig,
    stop: asyncio.Event,
    tally: Tally,
    count: int,
    rate: float,
    room_of: Any,
) -> None:
    """Open ``count`` connections at ``rate`` a second, each held by its own task.

    ``room_of(i)`` is the room connection ``i`` joins, or None: it never says hello.
    """
    ready()
    start = time.monotonic()

    async def one(i: int) -> None:
        try:
            ws = await _connect(cfg, i=i)
            room = room_of(i)
            if room is not None:
                await ws.send(_HELLO)
                await ws.recv()
                await ws.send(_frame("join", room=room, streams=["head"], rate=5.0))
            tally.sent["connection"] += 1
        except ConnectionClosed:
            tally.sent["connection"] += 1
            tally.closed(ws)
            return
        except (OSError, WebSocketException, TimeoutError) as exc:
            tally.extra.setdefault("connect_failures", Counter())[type(exc).__name__] += 1
            return
        await _hold(ws, stop, tally)

    async with asyncio.TaskGroup() as tg:
        for i in range(count):
            if stop.is_set():
                break
            tg.create_task(one(i))
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(
                    stop.wait(), max(0.0, start + (i + 1) / rate - time.monotonic())
                )


async def _flood(cfg: AttackConfig, stop: asyncio.Event, tally: Tally) -> None:
    """Connections from one address that never say hello nor join."""
    await _open_paced(cfg, stop, tally, cfg.flood_connections, cfg.flood_rate, lambda i: None)


async def _rooms(cfg: AttackConfig, stop: asyncio.Event, tally: Tally) -> None:
    """Connections that each join a room of their own (``spam-0``, ``spam-1``, ...)."""
    await _open_paced(cfg, stop, tally, cfg.rooms, cfg.rooms_rate, lambda i: f"spam-{i}")


async def _never_reader(cfg: AttackConfig, stop: asyncio.Event, tally: Tally) -> None:
    """A member that joins at 30 Hz and then never reads its socket (small receive buffer)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.bind((cfg.address, 0))
    sock.setblocking(False)
    host, port = cfg.url.removeprefix("ws://").rsplit(":", 1)
    await asyncio.get_running_loop().sock_connect(sock, (host, int(port)))
    ws = await _connect(cfg, sock)
    await _join(ws, cfg.room, ("head",), 30.0)
    ready()
    tally.sent["join"] += 1
    await stop.wait()  # never calls ws.recv(): the server's writes back up
    rcvd = ws.protocol.close_rcvd
    tally.extra["closed_by_server"] = rcvd is not None
    tally.closes[str(rcvd.code) if rcvd is not None else "held to the end"] += 1
    ws.transport.abort()


_RUNNERS: dict[str, Any] = {
    "timestamp": _timestamp,
    "lag-liar": _timestamp,
    "fuzz": _fuzz,
    "flood": _flood,
    "never-reader": _never_reader,
    "rooms": _rooms,
}


def ready(**extra: object) -> None:
    """Tell the controller the attack is in place (and ``extra``, e.g. a proxy's port)."""
    print(json.dumps({"event": "attacking", **extra}), flush=True)


async def go(cfg: AttackConfig, stop: asyncio.Event) -> None:
    """Wait for the controller's ``cfg.wait_for`` signal (or the end), if any."""
    if cfg.wait_for is not None:
        began = asyncio.create_task(signal(cfg.wait_for).wait())
        ended = asyncio.create_task(stop.wait())
        await asyncio.wait([began, ended], return_when=asyncio.FIRST_COMPLETED)
        began.cancel()
        ended.cancel()


#: Signals from the controller (``{"signal": NAME}`` lines on stdin), by name.
_SIGNALS: dict[str, asyncio.Event] = {}


def signal(name: str) -> asyncio.Event:
    """The event the controller's signal ``name`` sets (e.g. ``cut``: the blackhole)."""
    return _SIGNALS.setdefault(name, asyncio.Event())


def _set_signal(name: str) -> None:
    signal(name).set()
