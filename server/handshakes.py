"""Connections before their websocket handshake: counted, bounded, and never the last fd.

A TCP connection costs a file descriptor and a parser from ``accept`` on, long
before the core sees it (``RelayCore.connect`` runs once the handshake is done).
3,000 slow upgrade requests (1 byte a second) held 3,018 fds and, under a
``nofile`` limit of 1,024, locked every new user and ``/healthz`` out. So:

- a connection is counted from ``accept`` (:meth:`Handshakes.admit`) until its
  handshake ends (:meth:`Handshakes.release`): pending ones count against
  ``max_connections`` and ``max_connections_per_address`` with the open ones;
- over a cap, it gets one of ``HEALTH_RESERVE`` spare places, where
  ``GET /healthz`` and ``GET /metrics`` are answered and a websocket is closed
  1013 "try again later" right after its handshake (as over the caps of open
  connections), or, with no spare place either, it is dropped at once;
- its handshake must end within ``handshake_timeout`` (2 s by default; it was 10 s);
- at the total cap, a new connection takes the place of the oldest pending
  handshake if that one has been pending ``EVICT_AFTER`` (0.5 s) or more: slow
  upgrades from many addresses (each under its own cap) then cannot fill the relay
  and lock honest users out, whose handshakes take milliseconds, not seconds;
- the adapter (``server/app.py``'s ``fd_budget``) raises the process's ``nofile``
  soft limit to its hard limit and lowers the caps so that ``FD_RESERVE``
  descriptors always stay free (for the spare places, recordings, the cluster's
  NATS, the log).

Refusals are counted (``posecast_handshakes_refused_total``) and logged at most
once a second with a count of those not logged (``Log`` lines the adapter takes with
:meth:`Handshakes.take_logs`). Sans I/O: the adapter passes the time.
"""

from __future__ import annotations

from typing import Literal

from posecast.server.actions import WARNING, Log
from posecast.server.guard import Guard
from posecast.server.limits import Admission
from posecast.server.logs import LogLimiter

__all__ = ["EVICT_AFTER", "FD_RESERVE", "HEALTH_RESERVE", "Handshakes"]


#: Spare places over the connection caps where only /healthz and /metrics are answered.
HEALTH_RESERVE = 16
#: File descriptors kept free beyond every connection the caps allow.
FD_RESERVE = 64
#: At the total cap, a pending handshake this old (s) gives its place to a new one.
EVICT_AFTER = 0.5

Slot = Literal["handshake", "probe"]


class Handshakes:
    """TCP connections whose handshake is under way, in total and per address."""

    def __init__(
        self, admission: Admission, reserve: int = HEALTH_RESERVE, guard: Guard | None = None
    ) -> None:
        #: The core's open connections (its caps are the caps of both).
        self.admission = admission
        self.reserve = reserve
        self.pending = 0
        self.by_address: dict[str, int] = {}
        #: Connections over a cap answered on a spare place (HTTP only).
        self.probes = 0
        #: Dropped at once (over a cap, no spare place), and dropped for not
        #: finishing their handshake in time.
        self.refused = self.timeouts = 0
        #: Pending handshakes dropped for a new connection at the total cap.
        self.evicted = 0
        self.evict_after = EVICT_AFTER
        #: Pending handshakes admitted with a key, oldest first: key -> (address, since).
        self._order: dict[object, tuple[str | None, float]] = {}
        self._evicted: list[object] = []
        self._log = LogLimiter(1.0)
        self._logs: list[Log] = []
        #: Rates across connections, per address and token user (``server/guard.py``).
        self.guard = guard or Guard()

    def admit(self, address: str | None, now: float, key: object = None) -> Slot | None:
        """Count a new TCP connection from ``address``: ``"handshake"`` (within the caps),
        ``"probe"`` (over one: a spare place, plain HTTP only) or None (drop it now).

        ``key`` (the adapter's connection) lets a later connection at the total cap take
        its place once it has been pending ``evict_after`` s; :meth:`take_evicted` then
        names it, and the adapter drops it."""
        cap = self.admission
        full = bool(cap.max_total) and self.pending + cap.total >= cap.max_total
        oldest = self._oldest(now) if full else None
        if full and oldest is None:
            return self._over(address, now)
        if not self.guard.connect(address, now):  # reconnecting too fast
            return self._over(address, now)
        if address is not None and cap.max_per_address:
            held = self.by_address.get(address, 0) + cap.by_address.get(address, 0)
            if held >= cap.max_per_address:
                return self._over(address, now)
        if oldest is not None:
            self._evict(oldest, now)
        self.pending += 1
        if address is not None:
            self.by_address[address] = self.by_address.get(address, 0) + 1
        if key is not None:
            self._order[key] = (address, now)
        return "handshake"

    def _oldest(self, now: float) -> object | None:
        """The key of the oldest pending handshake if it has waited ``evict_after`` s."""
        key = next(iter(self._order), None)
        if key is None or now - self._order[key][1] < self.evict_after:
            return None
        return key

    def _evict(self, key: object, now: float) -> None:
        """Give up the pending handshake ``key`` (:meth:`_oldest`) for a new one."""
        address, _ = self._order.pop(key)
        self._count_off(address)
        self._evicted.append(key)
        self.evicted += 1
        quiet = self._log.admit(now)
        if quiet is not None:
            self._logs.append(Log(
                WARNING,
                "at the connection cap (%d): the oldest pending handshake (from %s) "
                "gave its place to a new connection%s",
                (self.admission.max_total, address, self._log.note(quiet)),
            ))  # fmt: skip

    def take_evicted(self) -> list[object]:
        """The keys of the pending handshakes given up since the last call (drop them)."""
        out, self._evicted = self._evicted, []
        return out

    def take_logs(self) -> list[Log]:
        """The log lines decided since the last call (the adapter logs them)."""
        out, self._logs = self._logs, []
        return out

    def _over(self, address: str | None, now: float) -> Slot | None:
        cap = self.admission
        if self.probes < self.reserve:
            self.probes += 1
            return "probe"
        self.refused += 1
        quiet = self._log.admit(now)
        if quiet is not None:
            self._logs.append(Log(
                WARNING,
                "connection from %s dropped before its handshake: %d pending, %d open, "
                "caps %d in all and %d per address%s",
                (address, self.pending, cap.total, cap.max_total, cap.max_per_address,
                 self._log.note(quiet)),
            ))  # fmt: skip
        return None

    def release(self, slot: Slot, address: str | None, key: object = None) -> None:
        """A connection :meth:`admit` counted has finished its handshake, or ended."""
        if slot == "probe":
            self.probes -= 1
            return
        if key is not None and self._order.pop(key, None) is None:
            return  # given up at the cap: no longer counted
        self._count_off(address)

    def _count_off(self, address: str | None) -> None:
        self.pending -= 1
        if address is not None:
            left = self.by_address.pop(address, 1) - 1
            if left > 0:
                self.by_address[address] = left
