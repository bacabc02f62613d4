"""The load process of ``posecast bench relay``: every client in one asyncio loop.

Run as a subprocess by the controller (:data:`posecast.bench.common._LOAD_BOOT`).
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

import msgpack
import numpy as np

from posecast.bench.common import (
    _FLUSH_EVERY,
    STREAMS,
    _pct,
    _raise_nofile,
    _run_loop,
    _ws_header,
    update_template,
)
from protocol import SNAPSHOT_DTYPE, SNAPSHOT_ENTRY_SIZE
from server.room import room_phase


class _LoadStats:
    """What the load measures; only arrivals inside the window count."""

    def __init__(self, clients: int, rate: float) -> None:
        self.rate = rate
        self.t0 = math.inf
        self.t1 = math.inf
        self.snapshots_total = np.zeros(clients, dtype=np.int64)
        self.snapshots = np.zeros(clients, dtype=np.int64)
        self.updates = 0
        self.updates_total = 0
        self.sends_late = 0
        self.payload_bytes = 0
        self.wire_bytes = 0
        self.other_frames = 0
        self.bad_frames = 0
        self.poses_all = 0
        self.poses_remote = 0
        # Per-snapshot scalars waiting to be flushed into arrays.
        self._bodies: list[bytes] = []
        self._owner: list[int] = []
        self._send: list[float] = []
        self._due: list[float] = []
        self._arrival: list[float] = []
        self._lat: list[np.ndarray] = []
        self._hold: list[np.ndarray] = []
        self._relay: list[np.ndarray] = []
        self._tick_lag: list[np.ndarray] = []
        self._gap: list[float] = []

    def in_window(self, t: float) -> bool:
        return self.t0 <= t < self.t1

    def snapshot(
        self, index: int, user: int, arrival: float, send: float, due: float, body: bytes, size: int
    ) -> None:
        self.snapshots_total[index] += 1
        if not self.t0 <= arrival < self.t1:
            return
        self.snapshots[index] += 1
        self.payload_bytes += size
        self.wire_bytes += size + _ws_header(size)
        self._bodies.append(body)
        self._owner.append(user)
        self._send.append(send)
        self._due.append(due)
        self._arrival.append(arrival)
        if len(self._bodies) >= _FLUSH_EVERY:
            self.flush()

    def sent(self, scheduled: float, now: float) -> None:
        self.updates_total += 1
        if self.t0 <= now < self.t1:
            self.updates += 1
            self._gap.append(now - scheduled)

    def flush(self) -> None:
        if not self._bodies:
            return
        counts = np.fromiter((len(b) // SNAPSHOT_ENTRY_SIZE for b in self._bodies), np.int64)
        entries = np.frombuffer(b"".join(self._bodies), dtype=SNAPSHOT_DTYPE)
        send = np.asarray(self._send, dtype=np.float64)
        arrival = np.asarray(self._arrival, dtype=np.float64)
        owner = np.repeat(np.asarray(self._owner, dtype=np.int64), counts)
        due = np.asarray(self._due, dtype=np.float64)
        remote = entries["user"].astype(np.int64) != owner
        dt = entries["dt"].astype(np.float64)[remote]
        capture = np.repeat(send, counts)[remote] + dt
        self._lat.append(((np.repeat(arrival, counts)[remote] - capture) * 1e3).astype(np.float32))
        self._hold.append(((np.repeat(due, counts)[remote] - capture) * 1e3).astype(np.float32))
        self._relay.append(((arrival - due) * 1e3).astype(np.float32))
        self._tick_lag.append(((send - due) * 1e3).astype(np.float32))
        self.poses_all += len(entries)
        self.poses_remote += int(remote.sum())
        self._bodies.clear()
        self._owner.clear()
        self._send.clear()
        self._due.clear()
        self._arrival.clear()

    def summary(self) -> dict[str, Any]:
        self.flush()

        def cat(parts: list[np.ndarray]) -> np.ndarray:
            return np.concatenate(parts) if parts else np.zeros(0, np.float32)

        lat, hold, relay, lag = (
            cat(self._lat),
            cat(self._hold),
            cat(self._relay),
            cat(self._tick_lag),
        )
        gap = np.asarray(self._gap, dtype=np.float64) * 1e3
        window = self.t1 - self.t0
        per_client = self.snapshots / window if window > 0 else self.snapshots * 0.0
        return {
            "window_s": window,
            "snapshots": int(self.snapshots.sum()),
            "snapshots_per_client_s": float(per_client.mean()) if len(per_client) else 0.0,
            "snapshots_per_client_s_min": float(per_client.min()) if len(per_client) else 0.0,
            "snapshots_per_client_s_max": float(per_client.max()) if len(per_client) else 0.0,
            "clients_without_snapshots": int((self.snapshots_total == 0).sum()),
            "clients_without_snapshots_in_window": int((self.snapshots == 0).sum()),
            "poses_delivered": self.poses_remote,
            "poses_delivered_incl_own": self.poses_all,
            "payload_bytes": self.payload_bytes,
            "wire_bytes": self.wire_bytes,
            "updates_sent": self.updates,
            "updates_sent_total": self.updates_total,
            "sends_late": self.sends_late,
            "send_lag_p99_ms": _pct(gap, 99),
            "latency_p50_ms": _pct(lat, 50),
            "latency_p99_ms": _pct(lat, 99),
            "latency_max_ms": float(lat.max()) if len(lat) else math.nan,
            "hold_p50_ms": _pct(hold, 50),
            "hold_p99_ms": _pct(hold, 99),
            "relay_p50_ms": _pct(relay, 50),
            "relay_p99_ms": _pct(relay, 99),
            "relay_max_ms": float(relay.max()) if len(relay) else math.nan,
            "tick_lag_p50_ms": _pct(lag, 50),
            "tick_lag_p99_ms": _pct(lag, 99),
            "other_frames": self.other_frames,
            "bad_frames": self.bad_frames,
        }


class _BenchClient:
    """One load client: handshake, then publish and receive until cancelled."""

    def __init__(self, index: int, room: str, rate: float, stats: _LoadStats) -> None:
        self.index = index
        self.room = room
        self.rate = rate
        self.stats = stats
        self.settled = asyncio.Event()
        self.error: str | None = None
        self.ws: Any = None

    async def run(self, url: str, rng: random.Random) -> None:
        from client.connection import ClientConnection

        try:
            conn = await ClientConnection.open(
                url,
                room=self.room,
                streams=STREAMS,
                rate=self.rate,
                agent="posecast-bench",
                open_timeout=15.0,
            )
        except Exception as exc:
            self.error = f"{type(exc).__name__}: {exc}"
            self.settled.set()
            return
        self.ws = conn.ws
        assert conn.joined is not None
        ids = [conn.joined.streams[name] for name in STREAMS]
        wire = update_template(ids, (0.01 * self.index, 1.6, 0.0))
        self.settled.set()
        async with asyncio.TaskGroup() as tg:
            tg.create_task(self._publish(wire, rng.random()))
            tg.create_task(self._receive(conn.user))

    async def _publish(self, wire: dict[str, Any], phase: float) -> None:
        from websockets.exceptions import ConnectionClosed

        ws, stats, pack = self.ws, self.stats, msgpack.packb
        period = 1.0 / self.rate
        due = time.monotonic() + phase * period
        seq = 0
        with contextlib.suppress(ConnectionClosed):
            while True:
                delay = due - time.monotonic()
                if delay > 0:
                    await asyncio.sleep(delay)
                now = time.monotonic()
                seq += 1
                wire["seq"] = seq
                wire["time"] = now
                await ws.send(pack(wire))
                stats.sent(due, now)
                due += period
                if due < now:
                    # Behind by more than a period: skip, never burst.
                    missed = math.ceil((now - due) / period)
                    if stats.in_window(now):
                        stats.sends_late += missed
                    due += missed * period

    async def _receive(self, user: int) -> None:
        from websockets.exceptions import ConnectionClosed

        stats, unpack, index, rate = self.stats, msgpack.unpackb, self.index, self.rate
        floor = math.floor
        ph = room_phase(self.room)
        # The server ticks a subscriber on the grid (k + phase) / rate of its clock
        # (phase: the room's, see server.room.room_phase), and after
        # a tick at ``now`` its next one is due at the first grid point after
        # ``now`` (missed points are skipped). A snapshot's send time is the
        # ``now`` of its tick, so the due time of each snapshot follows from the
        # previous one's send time, even when ticks run more than a period late.
        prev: float | None = None
        with contextlib.suppress(ConnectionClosed):
            async for data in self.ws:
                arrival = time.monotonic()
                if not isinstance(data, bytes):
                    stats.bad_frames += 1
                    continue
                try:
                    wire = unpack(data)
                    if wire["type"] != "snapshot":
                        stats.other_frames += 1
                        continue
                    body, send = wire["poses"], float(wire["time"])
                    if type(body) is not bytes or len(body) % SNAPSHOT_ENTRY_SIZE:
                        raise ValueError("not whole snapshot records")
                except Exception:
                    stats.bad_frames += 1
                    continue
                latest = (floor(send * rate - ph + 1e-9) + ph) / rate
                due = latest if prev is None else (floor(prev * rate - ph + 1e-9) + 1 + ph) / rate
                if due > send:
                    due = latest
                prev = send
                stats.snapshot(index, user, arrival, send, due, body, len(data))


async def _load_main(cfg: dict[str, Any], emit: Callable[[dict[str, Any]], None]) -> None:
    loop = asyncio.get_running_loop()
    lines: asyncio.Queue[str | None] = asyncio.Queue()

    def read_stdin() -> None:
        for line in sys.stdin:
            loop.call_soon_threadsafe(lines.put_nowait, line)
        loop.call_soon_threadsafe(lines.put_nowait, None)

    threading.Thread(target=read_stdin, daemon=True).start()

    n, size, rate = int(cfg["clients"]), int(cfg["room_size"]), float(cfg["rate"])
    stats = _LoadStats(n, rate)
    rng = random.Random(int(cfg.get("seed", 0)))
    clients = [_BenchClient(i, f"bench-{i // size}", rate, stats) for i in range(n)]
    tasks: list[asyncio.Task[None]] = []
    try:
        start = time.monotonic()
        for i, client in enumerate(clients):
            delay = start + i / float(cfg["ramp_rate"]) - time.monotonic()
            if delay > 0:
                await asyncio.sleep(delay)
            tasks.append(asyncio.create_task(client.run(cfg["url"], rng)))
        pending = [asyncio.create_task(c.settled.wait()) for c in clients]
        _, still = await asyncio.wait(pending, timeout=30.0)
        for waiter in still:
            waiter.cancel()
        errors = [c.error for c in clients if c.error]
        emit(
            {
                "event": "ramped",
                "joined": sum(1 for c in clients if c.ws is not None),
                "failed": len(errors) + len(still),
                "errors": errors[:5],
                "ramp_s": time.monotonic() - start,
            }
        )
        line = await asyncio.wait_for(lines.get(), timeout=float(cfg["window_timeout"]))
        if line is None:
            return
        order = json.loads(line)
        if "window" not in order:
            return
        stats.t0, stats.t1 = (float(x) for x in order["window"])
        await asyncio.sleep(max(0.0, stats.t1 - time.monotonic()) + 0.05)
        summary = stats.summary()
        summary["crashed_clients"] = sum(
            1 for t in tasks if t.done() and not t.cancelled() and t.exception() is not None
        )
        summary["event"] = "result"
        emit(summary)
    finally:
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        open_ws = [c.ws for c in clients if c.ws is not None]
        if open_ws:
            await asyncio.wait(
                [asyncio.create_task(ws.close(1000, "bench over")) for ws in open_ws], timeout=10.0
            )


def _load_entry() -> None:
    """Entry of the load subprocess: config as JSON in argv[1], JSON lines on stdout."""
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
    _raise_nofile(int(cfg["clients"]) + 256)
    _run_loop(_load_main(cfg, emit))
