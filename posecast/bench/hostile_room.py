"""Attacks of issue 29 from inside the honest room: fuzzers, an event flood, churn.

Run by the attacker process of :mod:`posecast.bench.hostile_attacks` (which holds
the shared helpers and the lag-liar, a variant of its timestamp attack):

- ``fuzz-in-room``: ``room_fuzzers`` members of the honest room, half of them
  coding compact, sending mutated raw and compact updates, joins, events, and
  the types only a server sends (welcome, joined, snapshot, ...), with values no
  client would send (e.g. a capture time of 1e300), reconnecting whenever the
  relay closes them; ``fuzz_frames`` frames in all, spread over the run;
- ``events-reconnect``: a member sending ``event_rate`` events a second that
  reconnects as soon as the relay closes it;
- ``churn``: valid joins of the honest room, each followed by a ``bye``,
  ``churn_rate`` a second (no bad frame at all).

Each is bounded by its time (``seconds``, or the controller closing stdin) and
its counts; what the relay answered is tallied (close codes, error codes).
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections import Counter
from typing import Any

import msgpack
import numpy as np
from websockets.asyncio.client import ClientConnection as WsConnection
from websockets.exceptions import ConnectionClosed, WebSocketException

from posecast.bench.hostile_attacks import (
    _POSE,
    AttackConfig,
    Tally,
    _connect,
    _count_replies,
    _frame,
    _join,
    go,
    ready,
)
from posecast.protocol import DEFAULT_VOLUME, encode_snapshot, encode_update
from posecast.protocol.codec import encode_update as encode_compact

__all__ = ["RUNNERS"]

#: Values no honest client sends, put in place of a field of a valid message.
_NASTY: tuple[object, ...] = (
    1e300,
    -1e300,
    1e240,
    float("inf"),
    float("-inf"),
    float("nan"),
    5e-324,
    2**64 - 1,
    -(2**63),
    -1,
    0,
    True,
    None,
    "",
    "x" * 300,
    "\u202e\u0000" * 40,
    b"\x00\xff" * 40,
    [],
    {},
    [[[[[[[[[[]]]]]]]]]],
    {"a": {"b": {"c": {"d": 1e300}}}},
    list(range(200)),
)
#: Types only the relay sends: a client sending one is refused.
_SERVER_TYPES = (
    "welcome",
    "joined",
    "peer_joined",
    "peer_left",
    "rate",
    "peer_stalled",
    "peer_resumed",
    "pong",
    "error",
)


def _corpus(room: str, ids: list[int], now: float) -> list[bytes]:
    """Valid frames of a member owning streams ``ids`` at server time ``now``:
    the seeds every mutant grows from."""
    n = len(ids)
    poses = np.tile(_POSE, (n, 1))
    times = np.full(n, now)
    compact = encode_compact(1, now, ids, times, poses, DEFAULT_VOLUME).data
    snapshot = encode_snapshot(1, now, [1] * n, ids, times, poses)
    server = [_frame(t, user=1, streams={"head": 1}, rate=10.0, seq=1) for t in _SERVER_TYPES]
    return [
        encode_update(1, ids, times, poses),
        compact,
        _frame("join", room=room, streams=["head", "left"], rate=10.0),
        _frame("event", kind="button", stream=ids[0], time=now, payload={"x": 1}),
        _frame("ping", seq=1, time=now),
        _frame("set_rate", rate=10.0),
        _frame("hello", version=1, agent="fuzz", resumable=True),
        snapshot,
        *server,
    ]


def _mutate_map(rng: np.random.Generator, data: bytes) -> bytes | None:
    """A msgpack map with one field replaced, dropped or added (None: not a map)."""
    try:
        msg = msgpack.unpackb(data, strict_map_key=False)
    except (ValueError, msgpack.ExtraData, TypeError):
        return None
    if not isinstance(msg, dict) or not msg:
        return None
    keys = list(msg)
    key = keys[int(rng.integers(len(keys)))]
    what = int(rng.integers(10))
    if what == 0:
        del msg[key]
    elif what == 1:
        msg[f"extra{int(rng.integers(1000))}"] = _NASTY[int(rng.integers(len(_NASTY)))]
    elif what == 2 and key != "type":
        msg["type"] = _SERVER_TYPES[int(rng.integers(len(_SERVER_TYPES)))]
    else:
        msg[key] = _NASTY[int(rng.integers(len(_NASTY)))]
    out: bytes = msgpack.packb(msg)
    return out


def _mutate_bytes(rng: np.random.Generator, data: bytes) -> bytes:
    """``data`` with bits flipped, a slice cut, bytes inserted or overwritten."""
    buf = bytearray(data)
    what = int(rng.integers(4))
    at = int(rng.integers(len(buf)))
    if what == 0:
        for _ in range(int(rng.integers(1, 5))):
            i = int(rng.integers(len(buf)))
            buf[i] ^= 1 << int(rng.integers(8))
    elif what == 1:
        del buf[at : at + int(rng.integers(1, 9))]
    elif what == 2:
        buf[at:at] = rng.bytes(int(rng.integers(1, 9)))
    else:
        buf[at : at + 8] = rng.bytes(8)
    return bytes(buf) or b"\x00"


def _mutant(rng: np.random.Generator, corpus: list[bytes]) -> tuple[str, bytes]:
    """One fuzzed frame of ``corpus`` and what kind it is."""
    i = int(rng.integers(len(corpus)))
    seed = corpus[i]
    if i >= len(corpus) - len(_SERVER_TYPES) and rng.random() < 0.5:
        return "server-type", seed
    if rng.random() < 0.6:
        mutated = _mutate_map(rng, seed)
        if mutated is not None:
            return "field-mutant", mutated
    return "byte-mutant", _mutate_bytes(rng, seed)


async def _pace(stop: asyncio.Event, rate: float, sent: int, start: float) -> None:
    """Wait until ``sent`` frames are due at ``rate`` a second from ``start`` (or stop);
    behind, still yield: a sender that never does starves its own reader (the close
    frames, the pings), and the relay's closes would go unseen."""
    ahead = start + sent / rate - time.monotonic()
    if ahead > 0:
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), ahead)
    else:
        await asyncio.sleep(0)


async def _session_end(
    ws: Any, reader: asyncio.Task[None], stop: asyncio.Event, tally: Tally
) -> None:
    """Count how a connection ended (the relay closed it, or we did) and let it go."""
    if not stop.is_set():  # closed under us: let the reader see the close frame
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(asyncio.shield(reader), 2.0)
    if ws.protocol.close_rcvd is not None:
        tally.closed(ws)
    elif reader.done() and not stop.is_set():  # the relay dropped it, no close frame
        tally.closes["dropped"] += 1
    else:
        tally.closes["closed by the attacker"] += 1
    if stop.is_set() or not reader.done():
        ws.transport.abort()
    await reader


def _failed(tally: Tally, exc: BaseException) -> None:
    tally.extra.setdefault("connect_failures", Counter())[type(exc).__name__] += 1
    if isinstance(exc, RuntimeError):  # a refused join: its code
        tally.errors[str(exc)] += 1


async def _member(
    cfg: AttackConfig,
    stop: asyncio.Event,
    tally: Tally,
    streams: tuple[str, ...],
    backoff: float,
    rate: float = 10.0,
    **join: object,
) -> tuple[WsConnection, float, list[int]] | None:
    """A new member of the honest room: (socket, server clock minus ours, stream ids);
    None if it could not connect or join (counted, then ``backoff`` s of waiting)."""
    try:
        ws = await _connect(cfg)
        offset, ids = await _join(ws, cfg.room, streams, rate, **join)
    except (OSError, RuntimeError, WebSocketException, TimeoutError) as exc:
        _failed(tally, exc)
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), backoff)
        return None
    tally.sent["join"] += 1
    return ws, offset, ids


async def _room_fuzzer(
    cfg: AttackConfig, stop: asyncio.Event, tally: Tally, k: int, start: float, rate: float
) -> None:
    """One member of the honest room fuzzing, rejoining whenever it is closed."""
    rng = np.random.default_rng(cfg.seed + 100 + k)
    codec = "compact" if k % 2 else "raw"
    while not stop.is_set() and sum(tally.sent.values()) < cfg.fuzz_frames:
        joined = await _member(cfg, stop, tally, ("head", "left"), 0.1, codec=codec)
        if joined is None:
            continue
        ws, offset, ids = joined
        reader = asyncio.create_task(_count_replies(ws, tally))
        corpus = _corpus(cfg.room, ids, time.monotonic() + offset)
        with contextlib.suppress(ConnectionClosed):
            while not stop.is_set() and not reader.done():
                for _ in range(8):
                    kind, data = _mutant(rng, corpus)
                    await ws.send(data)
                    tally.sent[kind] += 1
                total = sum(tally.sent.values())
                if total >= cfg.fuzz_frames:
                    break
                await _pace(stop, rate, total, start)
        await _session_end(ws, reader, stop, tally)


async def _fuzz_in_room(cfg: AttackConfig, stop: asyncio.Event, tally: Tally) -> None:
    """``room_fuzzers`` members fuzzing in the honest room, ``fuzz_frames`` in all."""
    ready()
    await go(cfg, stop)
    start = time.monotonic()
    rate = cfg.fuzz_rate if cfg.fuzz_rate > 0 else 1e9
    async with asyncio.TaskGroup() as tg:
        for k in range(cfg.room_fuzzers):
            tg.create_task(_room_fuzzer(cfg, stop, tally, k, start, rate))


async def _events_reconnect(cfg: AttackConfig, stop: asyncio.Event, tally: Tally) -> None:
    """A member sending ``event_rate`` button events a second, reconnecting when closed."""
    ready()
    await go(cfg, stop)
    start = time.monotonic()
    while not stop.is_set():
        joined = await _member(cfg, stop, tally, ("head",), 0.02, rate=5.0)
        if joined is None:
            continue
        ws, _, ids = joined
        reader = asyncio.create_task(_count_replies(ws, tally))
        frame = _frame("event", kind="button", stream=ids[0], payload={"button": 1})
        with contextlib.suppress(ConnectionClosed):
            while not stop.is_set() and not reader.done():
                for _ in range(50):
                    await ws.send(frame)
                tally.sent["event"] += 50
                await _pace(stop, cfg.event_rate, tally.sent["event"], start)
        await _session_end(ws, reader, stop, tally)


async def _join_and_leave(cfg: AttackConfig, tally: Tally, slots: asyncio.Semaphore) -> None:
    """One valid join of the honest room (head and hands), then ``bye`` and a close."""
    try:
        ws = await _connect(cfg)
        await _join(ws, cfg.room, ("head", "left", "right"), 10.0)
        tally.sent["join"] += 1
        await ws.send(_frame("bye", reason="churn"))
        tally.sent["bye"] += 1
        await ws.close()
        tally.closed(ws)
    except (OSError, RuntimeError, WebSocketException, TimeoutError) as exc:
        _failed(tally, exc)
    finally:
        slots.release()


async def _churn(cfg: AttackConfig, stop: asyncio.Event, tally: Tally) -> None:
    """``churn_rate`` joins (and leaves) a second, at most 32 under way at once."""
    ready()
    await go(cfg, stop)
    start = time.monotonic()
    slots = asyncio.Semaphore(32)
    async with asyncio.TaskGroup() as tg:
        i = 0
        while not stop.is_set() and i < cfg.churn_rate * cfg.seconds:
            await slots.acquire()
            tg.create_task(_join_and_leave(cfg, tally, slots))
            i += 1
            await _pace(stop, cfg.churn_rate, i, start)


RUNNERS = {
    "fuzz-in-room": _fuzz_in_room,
    "events-reconnect": _events_reconnect,
    "churn": _churn,
}
