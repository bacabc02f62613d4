"""A bot's own motion on the wire: its samples at the send rate, as pose updates.

:class:`Publisher` sends the newest sample of the bot's motion at each tick of its
send grid (capture times on the server's clock; a bot that fell behind resumes on
the grid, never bursts), with the velocity a tracker runtime could report at
capture time (:class:`CausalVelocities`) when it sends velocities, and with the
live scene's object while the bot holds it. It counts the update bytes and poses.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from functools import partial
from typing import Any

import numpy as np
from numpy.typing import NDArray

from posecast.client.connection import ClientConnection
from posecast.client.scene import ThrowCatchActor
from posecast.protocol import PoseUpdate, encode_update
from posecast.scenarios.motion import MotionSpec, sample_at
from posecast.scenarios.traces import CAUSAL_SAMPLES, Trace, causal_velocities

__all__ = ["CausalVelocities", "Publisher", "send_update"]


async def send_update(
    conn: ClientConnection,
    codec: str,
    seq: int,
    ids: NDArray[Any],
    captures: NDArray[np.float64],
    poses: NDArray[Any],
    velocities: NDArray[Any] | None = None,
) -> None:
    """One pose update on ``conn`` (capture times on the server's clock, based at the
    newest): ``raw`` records as they are, or ``compact``, which the session codes
    against what it sent before (per-stream baselines). The bot's publisher and the
    replay bots send through this."""
    args = (seq, ids, captures, np.asarray(poses, dtype=np.float32))
    base = float(captures.max())
    if codec == "raw":
        await conn.send_bytes(encode_update(*args, base_time=base, velocities=velocities))
    else:
        await conn.send(PoseUpdate.from_arrays(*args, base_time=base, velocities=velocities))


class CausalVelocities:
    """The causal velocity of each native sample of a trace, computed when first needed.

    Equal to ``trace.causal_velocities()[i]`` (the estimate at sample ``i`` only
    uses samples ``i - CAUSAL_SAMPLES + 1 .. i``), computed a chunk of samples at
    a time: a few milliseconds now and then instead of the whole trace up front.
    """

    CHUNK = 256

    def __init__(self, trace: Trace) -> None:
        self.trace = trace
        self._chunks: dict[int, NDArray[np.float64]] = {}

    def __getitem__(self, i: int) -> NDArray[np.float64]:
        c, k = divmod(i, self.CHUNK)
        chunk = self._chunks.get(c)
        if chunk is None:
            lo = c * self.CHUNK
            start = max(0, lo - (CAUSAL_SAMPLES - 1))  # the history the first sample needs
            hi = lo + self.CHUNK
            tr = self.trace
            chunk = causal_velocities(tr.times[start:hi], tr.poses[start:hi])[lo - start :]
            self._chunks[c] = chunk
        row: NDArray[np.float64] = chunk[k]
        return row


class Publisher:
    """A bot's motion ``trace`` (placed as ``spec`` says) published at ``send_rate``."""

    def __init__(
        self,
        trace: Trace,
        spec: MotionSpec,
        send_rate: float,
        *,
        codec: str = "compact",
        velocities: bool = False,
        actor: ThrowCatchActor | None = None,
    ) -> None:
        self.trace, self.spec, self.send_rate, self.codec = trace, spec, send_rate, codec
        self.actor = actor
        #: Causal velocities of its samples, if it sends them.
        self.velocities = CausalVelocities(trace) if velocities else None
        self.update_bytes = self.poses_sent = 0
        self._seq, self._last_sample = 0, -1.0

    async def run(self, conn: ClientConnection, stop: float, now: Callable[[], float]) -> None:
        """Publish on ``conn`` until server time ``stop`` (``now``: the server clock)."""
        t0, actor = self.spec.t0, self.actor
        period = 1.0 / self.send_rate
        self._seq, self._last_sample = 0, -1.0  # per connection, as the session counts
        k, nxt = 0, -np.inf
        while True:
            t = now()
            if t >= stop:
                return
            if actor is not None:  # the scene's actions, each at its own time
                for at, action in actor.due(t):
                    await actor.perform(conn, action, at, partial(self.send_sample, conn), t)
            if t >= nxt:
                await self.send_sample(conn, t)
                k += 1
                nxt = t0 + k * period
                if nxt <= t:  # fell behind: resume on the grid, never burst
                    k = int((t - t0) / period) + 1
                    nxt = t0 + k * period
            wake = nxt if actor is None else min(nxt, actor.next_at())
            await asyncio.sleep(max(0.0, wake - now()))

    async def send_sample(self, conn: ClientConnection, now: float) -> None:
        """Publish the newest sample at server time ``now``, unless it was sent (with the
        scene's object while this bot holds it)."""
        assert conn.joined is not None
        trace, t0, vel, actor = self.trace, self.spec.t0, self.velocities, self.actor
        idx, tm = sample_at(trace, max(0.0, now - t0))
        if tm == self._last_sample:
            return
        self._last_sample = tm
        cap = t0 + tm
        self._seq += 1
        ids = np.array([conn.joined.streams[n] for n in trace.streams])
        poses = trace.poses[idx]
        velocities = None if vel is None else vel[idx]
        drill = None if actor is None else actor.publishing(conn, cap)
        if actor is not None and drill is not None:
            ids = np.append(ids, drill)
            poses = np.concatenate([poses, actor.drill.poses[idx]])
            if velocities is not None:
                velocities = np.concatenate([velocities, actor.velocity(idx)[None]])
        before = conn.bytes_out
        caps = np.full(ids.size, cap)
        await send_update(conn, self.codec, self._seq, ids, caps, poses, velocities)
        self.update_bytes += conn.bytes_out - before
        self.poses_sent += ids.size
