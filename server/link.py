"""The relay's emulated downlink (``posecast serve --link``): its egress, sans I/O.

With ``ServerConfig.link`` set, every subscriber's snapshots go through a
:class:`Downlink` instead of straight to its socket: an :class:`EgressLink`
decides, frame by frame with the time passed in, whether the tier's bandwidth
lets the frame through, how long it is delayed (mean ``latency_ms``, standard
deviation ``jitter_ms``, right-skewed: ``latency - sqrt(2) jitter`` plus a
Gamma(k=2) draw) and whether it is lost; the frames in flight wait in a heap
(at most ``link_max_in_flight``, the oldest dropped past it) until they arrive.
Reliable messages (events, notices) never go through it. The rate the relay
serves the subscriber is what the cap affords (:meth:`EgressLink.rate_for`).

The delay distribution is the one of ``scenarios.network.LinkModel``, the
offline model of the same tiers; the tiers themselves (their data and loading)
are ``scenarios.network``'s: the relay takes any object with a tier's fields
(:class:`LinkTier`).
"""

from __future__ import annotations

import heapq
import math
from typing import Protocol

import numpy as np

__all__ = ["GAMMA_SHAPE", "WS_HEADER", "Downlink", "EgressLink", "LinkTier"]

#: Shape of the Gamma distribution of the variable part of the one-way delay.
GAMMA_SHAPE = 2.0
#: Websocket framing of a server frame of 126-65535 bytes (no mask): the link's extra.
WS_HEADER = 4


class LinkTier(Protocol):
    """What the relay needs of a network tier (``scenarios.network.Tier`` is one)."""

    @property
    def max_rate_hz(self) -> float: ...

    @property
    def latency_ms(self) -> float: ...

    @property
    def jitter_ms(self) -> float: ...

    @property
    def loss_pct(self) -> float: ...

    @property
    def bytes_per_s(self) -> float: ...


class EgressLink:
    """One subscriber's emulated downlink in a live server, frame by frame.

    The live counterpart of ``scenarios.network.LinkModel`` (same tier fields,
    same delay distribution), fed one frame at a time with the time passed in:
    :meth:`offer` says when the frame arrives, or ``None`` when it is skipped
    (the token bucket lacks its size: it is never queued behind the cap) or lost.
    :meth:`rate_for` is the update rate the cap allows for the frames seen so
    far, which the server adopts for this subscriber.
    """

    def __init__(self, tier: LinkTier, seed: int = 0, *, burst_bytes: float | None = None) -> None:
        self.tier = tier
        self._rng = np.random.default_rng(seed)
        self.burst_bytes = 0.05 * tier.bytes_per_s if burst_bytes is None else float(burst_bytes)
        self._tokens = 0.0
        self._t: float | None = None
        self._size_ema: float | None = None
        theta = tier.jitter_ms / 1000.0 / math.sqrt(GAMMA_SHAPE)
        self._theta = theta
        self._floor = tier.latency_ms / 1000.0 - GAMMA_SHAPE * theta
        self.frames = 0
        self.bytes = 0
        self.cap_skips = 0
        self.lost = 0

    def offer(self, now: float, size: int) -> float | None:
        """Arrival time of a ``size``-byte frame offered at ``now``; None if skipped or lost."""
        rate = self.tier.bytes_per_s
        burst = self.burst_bytes
        tokens = burst if self._t is None else min(burst, self._tokens + (now - self._t) * rate)
        self._t = now
        self._size_ema = size if self._size_ema is None else 0.9 * self._size_ema + 0.1 * size
        # A deficit bucket: a frame goes while the balance is not negative and is
        # charged in full (the balance may dip below zero), so the long-run rate
        # is exactly the cap and a burst never exceeds one frame over it.
        if tokens < 0.0:
            self._tokens = tokens
            self.cap_skips += 1
            return None
        self._tokens = tokens - size
        one_way = self._floor + (
            float(self._rng.gamma(GAMMA_SHAPE, self._theta)) if self._theta > 0 else 0.0
        )
        if self._rng.random() < self.tier.loss_pct / 100.0:
            self.lost += 1
            return None
        self.frames += 1
        self.bytes += size
        return now + one_way

    def rate_for(self, asked: float) -> float:
        """The rate to serve: what was asked, capped by the tier and by what its
        bandwidth affords for frames of the size seen so far."""
        tier = self.tier
        if self._size_ema is None:
            return min(asked, tier.max_rate_hz)
        return min(asked, tier.max_rate_hz, tier.bytes_per_s / self._size_ema)


class Downlink:
    """A subscriber's :class:`EgressLink` and the snapshots in flight on it."""

    def __init__(
        self, tier: LinkTier, seed: int, max_in_flight: int, *, in_order: bool = False
    ) -> None:
        self.link = EgressLink(tier, seed=seed)
        self.max_in_flight = max_in_flight
        #: Frames arrive in the order sent, as on a websocket: a frame delayed more
        #: than the next holds it back. Compact subscribers need it (each delta is
        #: coded against the frame before); raw ones keep the tier's own delays.
        self.in_order = in_order
        self._last_arrival = -math.inf
        #: (arrival, sequence, frame) of the frames on their way.
        self._in_flight: list[tuple[float, int, bytes]] = []
        self._seq = 0
        #: Frames dropped because ``max_in_flight`` were on their way already.
        self.overflow = 0

    def send(self, now: float, data: bytes) -> bool:
        """Put a snapshot on the link at ``now``; False if it never arrives (skipped
        or lost there, or, in order, refused while ``max_in_flight`` are on their way)."""
        arrival = self.link.offer(now, len(data) + WS_HEADER)
        if arrival is None:
            return False
        in_flight = self._in_flight
        if len(in_flight) >= self.max_in_flight:
            self.overflow += 1
            if self.in_order:  # the frames on their way are baselines: keep them
                return False
            heapq.heappop(in_flight)
        if self.in_order:
            arrival = self._last_arrival = max(arrival, self._last_arrival)
        self._seq += 1
        heapq.heappush(in_flight, (arrival, self._seq, data))
        return True

    def arrived(self, now: float, out: list[bytes]) -> None:
        """Append to ``out`` the frames that have arrived by ``now``, in arrival order."""
        in_flight = self._in_flight
        while in_flight and in_flight[0][0] <= now:
            out.append(heapq.heappop(in_flight)[2])

    def next_arrival(self) -> float | None:
        """When the next frame in flight arrives (None: nothing in flight)."""
        return self._in_flight[0][0] if self._in_flight else None

    def rate_for(self, asked: float) -> float:
        return self.link.rate_for(asked)
