"""The bare baseline of ``posecast bench relay --baseline``: broadcast, no rules.

What a websockets + uvloop server spends on the relay's fan-out when it does
nothing else: rooms of N, each client's latest update fanned to its room at the
tick rate with ``websockets.broadcast``. It speaks just enough of the protocol
for the bench's load (hello -> welcome, join -> joined, raw updates in,
snapshots out), so the same load measures both servers the same way. It keeps
no limits, no validation beyond what msgpack needs, no latest-wins slot, no
event queue, no skips, no recorder tap, no /metrics: a floor, not a relay.

Ticks follow the relay's schedule (the grid ``(k + room_phase) / rate`` of the
monotonic clock, missed points skipped), each tick packs one snapshot of the
room's streams updated since its last tick (``protocol.pack_snapshot``, as the
relay does) and hands the same bytes to ``websockets.broadcast``.

Run as a subprocess (``_baseline_entry``): ``--rate HZ``; prints the line
``posecast listening on ws://127.0.0.1:PORT`` once it listens and exits 0 on
SIGTERM or SIGINT.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import heapq
import math
import signal
import struct
import sys
import time
from dataclasses import dataclass, field
from typing import Any

import msgpack
from websockets.asyncio.server import ServerConnection, broadcast, serve
from websockets.exceptions import ConnectionClosed

from posecast.bench.common import _run_loop
from posecast.protocol import ErrorMessage, Hello, Join, Joined, Welcome, pack_snapshot
from posecast.protocol.wire import decode_message, encode_message
from posecast.server.room import room_phase

__all__ = ["BaselineServer"]

_UPDATE_HEAD = struct.Struct("<Hf")
_UPDATE_ENTRY = 34  # stream u16, dt f4, pose 7 x f4 (protocol.UPDATE_DTYPE)
_POSE = 28


@dataclass
class _Room:
    name: str
    rate: float
    phase: float
    members: dict[ServerConnection, int] = field(default_factory=dict)
    #: stream id -> (user, capture time, pose bytes), the newest of each stream.
    streams: dict[int, tuple[int, float, bytes]] = field(default_factory=dict)
    fresh: set[int] = field(default_factory=set)
    next_stream: int = 0
    tick: int = 0

    def grid_after(self, now: float) -> float:
        return (math.floor(now * self.rate - self.phase + 1e-9) + 1 + self.phase) / self.rate


class BaselineServer:
    """Rooms, a tick heap, and one handler per connection."""

    def __init__(self, rate: float) -> None:
        self.rate = rate
        self.rooms: dict[str, _Room] = {}
        self.next_user = 1
        self._dues: list[tuple[float, int, _Room]] = []
        self._seq = 0
        self._wake = asyncio.Event()
        self.snapshots = 0

    async def handler(self, ws: ServerConnection) -> None:
        with contextlib.suppress(ConnectionClosed, TimeoutError):
            await self._serve(ws)

    async def _serve(self, ws: ServerConnection) -> None:
        user = self.next_user
        self.next_user += 1
        hello = decode_message(await asyncio.wait_for(ws.recv(), 10.0))
        if not isinstance(hello, Hello):
            await ws.close(1008, "hello first")
            return
        lo, hi = min(5.0, self.rate), max(30.0, self.rate)
        welcome = Welcome(user=user, server_time=time.monotonic(), min_rate=lo, max_rate=hi)
        await ws.send(encode_message(welcome))
        join = decode_message(await asyncio.wait_for(ws.recv(), 10.0))
        if not isinstance(join, Join) or join.codec != "raw" or join.auto_rate:
            why = "the baseline takes raw updates at a fixed rate only"
            why = why if isinstance(join, Join) else "join next"
            await ws.send(encode_message(ErrorMessage(code="bad-message", message=why)))
            await ws.close(1008, why)
            return
        room = self._room(join.room, float(join.rate))
        ids = {name: room.next_stream + k for k, name in enumerate(join.streams)}
        room.next_stream += len(ids)
        await ws.send(encode_message(Joined(room=room.name, streams=ids, rate=float(join.rate))))
        room.members[ws] = user
        if len(room.members) == 1:
            self._schedule(room, room.grid_after(time.monotonic()))
        try:
            await self._receive(ws, room, user)
        finally:
            del room.members[ws]

    async def _receive(self, ws: ServerConnection, room: _Room, user: int) -> None:
        unpack, head = msgpack.unpackb, _UPDATE_HEAD
        async for data in ws:
            try:
                wire = unpack(data)
                if wire["type"] != "update":
                    continue
                base, body = float(wire["time"]), wire["poses"]
            except Exception:  # the load sends updates only; anything else is dropped
                continue
            streams, fresh = room.streams, room.fresh
            for off in range(0, len(body) - _UPDATE_ENTRY + 1, _UPDATE_ENTRY):
                sid, dt = head.unpack_from(body, off)
                streams[sid] = (user, base + dt, body[off + 6 : off + 6 + _POSE])
                fresh.add(sid)

    def _room(self, name: str, rate: float) -> _Room:
        room = self.rooms.get(name)
        if room is None:
            room = self.rooms[name] = _Room(name, rate, room_phase(name))
        return room

    def _schedule(self, room: _Room, due: float) -> None:
        self._seq += 1
        heapq.heappush(self._dues, (due, self._seq, room))
        self._wake.set()

    async def tick_loop(self) -> None:
        """Tick every room at its due times, for ever."""
        dues = self._dues
        while True:
            if not dues:
                self._wake.clear()
                await self._wake.wait()
                continue
            delay = dues[0][0] - time.monotonic()
            if delay > 0:
                # A room that joins meanwhile may be due sooner: its first tick is
                # then late by less than a period, during the ramp only.
                await asyncio.sleep(delay)
                continue
            now = time.monotonic()
            while dues and dues[0][0] <= now + 1e-9:
                room = heapq.heappop(dues)[2]
                if room.members:
                    self._tick(room, now)
                    self._schedule(room, room.grid_after(now))

    def _tick(self, room: _Room, now: float) -> None:
        if not room.fresh:
            return
        streams = room.streams
        entries = [(streams[sid][0], sid, streams[sid][1], streams[sid][2]) for sid in room.fresh]
        room.fresh.clear()
        room.tick += 1
        broadcast(room.members, pack_snapshot(room.tick, now, entries))
        self.snapshots += 1


async def _main(rate: float, host: str) -> None:
    server = BaselineServer(rate)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    async with asyncio.TaskGroup() as tg:
        ticks = tg.create_task(server.tick_loop())
        async with serve(server.handler, host, 0, compression=None, max_size=2**20) as ws_server:
            port = next(iter(ws_server.sockets)).getsockname()[1]
            print(f"posecast listening on ws://{host}:{port}", flush=True)
            await stop.wait()
        ticks.cancel()


def _baseline_entry(argv: list[str] | None = None) -> None:
    """Entry of the baseline subprocess."""
    parser = argparse.ArgumentParser(prog="posecast-bench-baseline")
    parser.add_argument("--rate", type=float, default=20.0, help="Tick rate (Hz).")
    parser.add_argument("--host", default="127.0.0.1", help="Address to listen on.")
    args: Any = parser.parse_args(sys.argv[1:] if argv is None else argv)
    if not 0 < args.rate <= 100:
        parser.error("--rate must be in (0, 100] Hz")
    _run_loop(_main(args.rate, args.host))
