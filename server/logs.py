"""Logging what peers cause without letting a peer fill the disk."""

from __future__ import annotations

from collections.abc import Callable

__all__ = ["LogLimiter"]


class LogLimiter:
    """At most one log record per ``interval`` seconds; counts the ones held back.

    Pure: time comes from ``clock`` only. :meth:`admit` before each record says
    whether to log it, and how many were held back since the previous logged one
    (:meth:`note` words that count); :meth:`flush` hands over the count still
    held back, e.g. when the connection ends.
    """

    def __init__(self, interval: float = 1.0, clock: Callable[[], float] | None = None) -> None:
        if not interval >= 0:
            raise ValueError(f"interval must be >= 0, got {interval}")
        self.interval = interval
        self.clock = clock
        self._last: float | None = None
        self._held = 0
        #: Seconds from the previous logged record to the last admit() or flush().
        self.span = 0.0
        #: Records held back so far, in all.
        self.suppressed = 0

    def _now(self, now: float | None) -> float:
        if now is not None:
            return now
        if self.clock is None:
            raise ValueError("LogLimiter without a clock needs the time")
        return self.clock()

    def admit(self, now: float | None = None) -> int | None:
        """None: hold this record back (it is counted). Otherwise log it: the
        number held back since the previous logged record (0 if none)."""
        t = self._now(now)
        if self._last is not None and t - self._last < self.interval:
            self._held += 1
            self.suppressed += 1
            return None
        held, self._held = self._held, 0
        self.span = 0.0 if self._last is None else t - self._last
        self._last = t
        return held

    def flush(self, now: float | None = None) -> int:
        """The number held back since the last logged record; the count restarts."""
        held, self._held = self._held, 0
        self.span = 0.0 if self._last is None else self._now(now) - self._last
        return held

    def note(self, held: int) -> str:
        """`` (and N more in the last S s)`` for a count held back, else ``""``."""
        if held <= 0:
            return ""
        return f" (and {held} more in the last {self.span:.1f} s)"
