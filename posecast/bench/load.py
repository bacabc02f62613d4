"""A load process of ``posecast bench relay``: its share of the clients in one asyncio loop.

Run as a subprocess by the controller (:data:`posecast.bench.common._LOAD_BOOT`),
one per ``--procs``. Each client is a :class:`~posecast.bench.wsclient.FrameConnection`
(no task of its own): one publisher task sends every client's pre-encoded
update at its phase of the period, and received frames are counted in the
connection's ``data_received``:

- a raw snapshot's header is parsed in place (its send time and the size of its
  records), its own-echo records are found by their 4-byte (user, stream)
  prefix, and the records themselves are left undecoded, except in one
  snapshot of every :data:`SAMPLE_EVERY` of a client, whose poses' capture
  times give the capture -> receipt latency;
- anything else (a codec snapshot, a velocity snapshot, a control message) is
  decoded by the protocol (a codec snapshot must be: its deltas need the
  client's baselines).

Relay latency (due tick -> receipt) and tick lag (send time - due tick) are kept
for every snapshot, as float64 arrays; the window's samples go to an ``.npz``
file the controller merges across processes. The client, its join and its frame
counting are :mod:`posecast.bench.loadclient`; this module drives them.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import os
import random
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from posecast.bench.common import (
    STATIC,
    Motion,
    _raise_nofile,
    _run_loop,
)
from posecast.bench.loadclient import (
    HUNG,
    JOINED,
    SERVER_FULL,
    RoomTicks,
    _BenchClient,
    _LoadStats,
)

#: Publish phases per period: clients due in one bucket are sent together.
BUCKETS = 64


class _Publisher:
    """One task sends every joined client's update at its phase of the period."""

    def __init__(self, rate: float, stats: _LoadStats, rng: random.Random) -> None:
        self.period = 1.0 / rate
        self.stats = stats
        self.rng = rng
        self.buckets: list[list[_BenchClient]] = [[] for _ in range(BUCKETS)]

    def add(self, client: _BenchClient) -> None:
        self.buckets[self.rng.randrange(BUCKETS)].append(client)

    async def run(self) -> None:
        stats, period, clock = self.stats, self.period, time.monotonic
        step = period / BUCKETS
        start = clock()
        while True:
            for b, bucket in enumerate(self.buckets):
                due = start + b * step
                delay = due - clock()
                if delay > 0:
                    await asyncio.sleep(delay)
                now = clock()
                skipped = sum(1 for c in bucket if not c.publish(clock()))
                stats.send_skips += skipped
                stats.sent_bucket(due, now, len(bucket) - skipped)
            start += period
            now = clock()
            if start + period < now:
                # Behind by more than a period: skip whole periods, never burst.
                missed = math.floor((now - start) / period)
                if stats.t0 <= now < stats.t1:
                    stats.sends_late += missed * sum(map(len, self.buckets))
                start += missed * period


async def _ramp(
    clients: list[_BenchClient], cfg: dict[str, Any], publisher: _Publisher
) -> dict[str, Any]:
    """Open every client at the ramp rate; the ``ramped`` message."""
    start = time.monotonic()
    ramp_rate = float(cfg["ramp_rate"])

    async def open_one(client: _BenchClient) -> None:
        await client.open(cfg["url"], float(cfg.get("open_timeout", 15.0)))
        if client.conn is not None:
            publisher.add(client)

    async with asyncio.TaskGroup() as tg:
        for i, client in enumerate(clients):
            delay = start + i / ramp_rate - time.monotonic()
            if delay > 0:
                await asyncio.sleep(delay)
            tg.create_task(open_one(client))
    return {"event": "ramped", **join_outcomes(clients), "ramp_s": time.monotonic() - start}


def measured_clients(clients: list[_BenchClient]) -> list[int]:
    """The clients whose snapshot rate is measured: those that joined a room another
    client joined too (a relay that refuses some joins leaves members alone in their
    room, and a lone member is sent nothing: no stream of others changes)."""
    rooms: dict[str, int] = {}
    for c in clients:
        if c.outcome == JOINED:
            rooms[c.room] = rooms.get(c.room, 0) + 1
    return [c.index for c in clients if c.outcome == JOINED and rooms[c.room] > 1]


def join_outcomes(clients: list[_BenchClient]) -> dict[str, Any]:
    """How the joins ended: joined, failed (refused by code, hung, ...), the step each
    hung join got no answer to, and how long each join, refusal (``server-full`` apart)
    and each client's TCP connect and websocket handshake took (s), to add up."""
    errors = [c.error for c in clients if c.error]
    codes: dict[str, int] = {}
    hung_at: dict[str, int] = {}
    for c in clients:
        if c.outcome and c.outcome != JOINED:
            codes[c.outcome] = codes.get(c.outcome, 0) + 1
        if c.outcome == HUNG:
            hung_at[c.hung_at] = hung_at.get(c.hung_at, 0) + 1
    return {
        "joined": sum(1 for c in clients if c.conn is not None),
        "failed": len(errors),
        "errors": errors[:5],
        "codes": codes,
        "hung": codes.get(HUNG, 0),
        "hung_at": hung_at,
        "join_s": [c.join_s for c in clients if c.outcome == JOINED],
        "refused_s": [c.join_s for c in clients if c.outcome not in ("", JOINED, HUNG)],
        "server_full_s": [c.join_s for c in clients if c.outcome == SERVER_FULL],
        "connect_s": [c.connect_s for c in clients if not math.isnan(c.connect_s)],
        "upgrade_s": [c.upgrade_s for c in clients if not math.isnan(c.upgrade_s)],
    }


async def _close_all(clients: list[_BenchClient], within: float) -> None:
    conns = [c.conn for c in clients if c.conn is not None]
    for conn in conns:
        conn.close(1000, "bench over")
    pending = [conn.closed for conn in conns if not conn.closed.done()]
    if pending:
        await asyncio.wait(pending, timeout=within)
    for conn in conns:
        conn.abort()


async def _load_main(cfg: dict[str, Any], emit: Callable[[dict[str, Any]], None]) -> None:
    loop = asyncio.get_running_loop()
    lines: asyncio.Queue[str | None] = asyncio.Queue(maxsize=16)

    def read_stdin() -> None:
        for line in sys.stdin:
            asyncio.run_coroutine_threadsafe(lines.put(line), loop).result()
        asyncio.run_coroutine_threadsafe(lines.put(None), loop).result()

    threading.Thread(target=read_stdin, daemon=True).start()
    first, last = int(cfg.get("first", 0)), int(cfg.get("last", cfg["clients"]))
    size, rate = int(cfg["room_size"]), float(cfg["rate"])
    # With ``members`` = [N, k] this process runs only the members j of each room
    # with j % N == k (``bench relay --nodes N``: node k's share).
    mod, keep = (int(x) for x in cfg.get("members", (1, 0)))
    chosen = [i for i in range(first, last) if (i % size) % mod == keep]
    stats = _LoadStats(len(chosen))
    codec = str(cfg.get("codec", "raw"))
    motion = Motion(str(cfg.get("motion", STATIC)), rate)
    offset = float(cfg.get("clock_offset", 0.0))
    rooms: dict[str, RoomTicks] = {}
    clients = [
        _BenchClient(
            n,
            name := f"bench-{i // size}",
            rate,
            stats,
            codec,
            motion.cycle(i),
            offset,
            rooms.setdefault(name, RoomTicks()),
        )
        for n, i in enumerate(chosen)
    ]
    publisher = _Publisher(rate, stats, random.Random(int(cfg.get("seed", 0)) * 1009 + first))
    try:
        async with asyncio.TaskGroup() as tg:
            pub = tg.create_task(publisher.run())
            emit(await _ramp(clients, cfg, publisher))
            if await _measure(cfg, stats, clients, lines, emit):
                # Keep the clients (and their load) on until the controller, which
                # samples the relay's end of the window after it, says it is done.
                await _until_eof(lines, float(cfg.get("window_timeout", 60.0)))
            pub.cancel()
    finally:
        await _close_all(clients, within=10.0)


async def _measure(
    cfg: dict[str, Any],
    stats: _LoadStats,
    clients: list[_BenchClient],
    lines: asyncio.Queue[str | None],
    emit: Callable[[dict[str, Any]], None],
) -> bool:
    """Wait for the window, count through it, write the samples and emit ``result``
    (False: the controller ended without a window)."""
    line = await asyncio.wait_for(lines.get(), timeout=float(cfg["window_timeout"]))
    if line is None:
        return False
    order = json.loads(line)
    if "window" not in order:
        return False
    stats.t0, stats.t1 = (float(x) for x in order["window"])
    await asyncio.sleep(max(0.0, stats.t1 - time.monotonic()) + 0.05)
    summary = stats.counts(measured_clients(clients))
    closed = [c.conn.closed.result() for c in clients if c.conn and c.conn.closed.done()]
    summary["clients_closed"] = len(closed)
    summary["close_reasons"] = sorted(set(closed))[:5]
    summary["load_clients"] = len(clients)
    samples = cfg.get("samples")
    if samples:
        arrays = stats.arrays()
        await asyncio.to_thread(
            np.savez,
            samples,
            latency=arrays["latency"],
            hold=arrays["hold"],
            relay=arrays["relay"],
            tick_lag=arrays["tick_lag"],
            send_lag=arrays["send_lag"],
            latency_sender=arrays["latency_sender"],
            latency_receiver=arrays["latency_receiver"],
        )
    summary["event"] = "result"
    emit(summary)
    return True


async def _until_eof(lines: asyncio.Queue[str | None], within: float) -> None:
    """Wait until the controller closes this process's stdin (at most ``within`` s)."""
    with contextlib.suppress(TimeoutError):
        async with asyncio.timeout(within):
            while await lines.get() is not None:
                pass


def _load_entry() -> None:
    """Entry of a load subprocess: config as JSON in argv[1], JSON lines on stdout."""
    cfg = json.loads(sys.argv[1])
    out = os.fdopen(os.dup(1), "w", buffering=1)
    sys.stdout = sys.stderr  # nothing else may write to the channel

    def emit(message: dict[str, Any]) -> None:
        out.write(json.dumps(message) + "\n")
        out.flush()

    def watchdog() -> None:
        time.sleep(float(cfg["hard_timeout"]))
        print("bench load: hard timeout, exiting", file=sys.stderr, flush=True)
        os._exit(3)

    threading.Thread(target=watchdog, daemon=True).start()
    _raise_nofile(int(cfg.get("last", cfg["clients"])) - int(cfg.get("first", 0)) + 256)
    with contextlib.suppress(KeyboardInterrupt):
        _run_loop(_load_main(cfg, emit))
