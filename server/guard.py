"""Limits that survive reconnects: rates per source address and per token user.

Every per-connection limit (the update bucket, the misbehaviour budget) starts
afresh on a new connection, so a peer that reconnects when closed defeats them
all: 10k events a second from one reconnecting member cut the honest keyframe
rate in half, and 57 valid joins and leaves a second tripled everyone's playout
delay (issue 29). These buckets are keyed by what a reconnect keeps, the source
address and (with ``--secret``) the token's user. The defaults are sized for many
users behind one address (a NAT, a load generator), so they bound an attacker's
aggregate rather than stop a small one:

==============  =====================  ==========================================
what            default (rate, burst)  over it
==============  =====================  ==========================================
connections     100/s per address      the connection gets a spare place
                                       (``server/handshakes.py``): closed 1013
                                       "try again later" after its handshake
joins           60/s per address       ``room-full`` "too many joins ... try
                and per token user     later" (non-fatal; charged to the budget)
events          1000/s per             the event is dropped and counted
                address and per token  (``flood_drops``); the connection is
                user                   closed 1008 "event flood"
==============  =====================  ==========================================

Each bucket holds 10 s worth (its burst). ``--max-connect-rate``, ``--max-join-rate``
and ``--max-event-rate`` set the rates; 0 turns that limit off. The tables are
bounded (``MAX_KEYS`` keys each: the least recently used key goes first), so many
addresses cannot grow them.
Sans-I/O: the time is an argument.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import Protocol

__all__ = ["MAX_KEYS", "Guard", "GuardLimits", "RateTable"]

#: Keys (addresses, users) one table remembers at most.
MAX_KEYS = 4096


class RateTable:
    """Token buckets of ``burst`` tokens refilled ``rate`` a second, one per key."""

    def __init__(self, rate: float, burst: float, max_keys: int = MAX_KEYS) -> None:
        self.rate = rate
        self.burst = burst
        self.max_keys = max_keys
        self._buckets: OrderedDict[str, tuple[float, float]] = OrderedDict()
        #: Times :meth:`take` said no.
        self.refused = 0

    def take(self, key: str, now: float) -> bool:
        """Spend one token of ``key``'s bucket; False (nothing spent) when it is empty."""
        if self.rate <= 0:
            return True
        buckets = self._buckets
        tokens, last = buckets.pop(key, (self.burst, now))
        tokens = min(self.burst, tokens + max(0.0, now - last) * self.rate)
        ok = tokens >= 1.0
        buckets[key] = (tokens - 1.0 if ok else tokens, max(last, now))
        if len(buckets) > self.max_keys:
            buckets.popitem(last=False)
        if not ok:
            self.refused += 1
        return ok

    def __len__(self) -> int:
        return len(self._buckets)


class Rates(Protocol):
    """What :meth:`Guard.of` reads of a ``ServerConfig``."""

    @property
    def max_connect_rate(self) -> float: ...
    @property
    def max_join_rate(self) -> float: ...
    @property
    def max_event_rate(self) -> float: ...


@dataclass(frozen=True)
class GuardLimits:
    """The defaults of the table in the module docstring."""

    connect_rate: float = 100.0
    connect_burst: float = 1000.0
    join_rate: float = 60.0
    join_burst: float = 600.0
    event_rate: float = 1000.0
    event_burst: float = 10000.0


class Guard:
    """The relay's rate tables across connections."""

    @classmethod
    def of(cls, cfg: Rates) -> Guard:
        """The guard of a relay's ``max_connect_rate``, ``max_join_rate`` and
        ``max_event_rate`` (bursts of 10 s worth)."""
        rates = cfg.max_connect_rate, cfg.max_join_rate, cfg.max_event_rate
        return cls(GuardLimits(*(x for r in rates for x in (r, 10 * r))))

    def __init__(self, limits: GuardLimits | None = None) -> None:
        lim = limits or GuardLimits()
        self.connects = RateTable(lim.connect_rate, lim.connect_burst)
        self.joins = RateTable(lim.join_rate, lim.join_burst)
        self.events = RateTable(lim.event_rate, lim.event_burst)
        #: Joins refused for their rate (``room-full``; in ``posecast_joins_refused_total``).
        self.joins_refused = 0

    @staticmethod
    def _keys(address: str | None, user: str | None) -> list[str]:
        keys = [] if address is None else [f"a:{address}"]
        return keys if user is None else [*keys, f"u:{user}"]

    def connect(self, address: str | None, now: float) -> bool:
        """A TCP connection from ``address`` may go on to its handshake."""
        return address is None or self.connects.take(f"a:{address}", now)

    def join(self, address: str | None, user: str | None, now: float) -> bool:
        """A join from ``address`` (by token ``user``, if any) may go on."""
        if all([self.joins.take(k, now) for k in self._keys(address, user)]):
            return True
        self.joins_refused += 1
        return False

    def event(self, address: str | None, user: str | None, now: float) -> bool:
        """An event from ``address`` (by token ``user``, if any) may be relayed."""
        return all([self.events.take(k, now) for k in self._keys(address, user)])
