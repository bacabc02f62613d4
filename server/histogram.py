"""The relay's histograms for Prometheus: counts per bucket, sums, their text.

``server.rates`` (auto rates) and ``server.view_rates`` (rates from an error
budget) each count the rates they choose in buckets (not cumulative) and write them
with :func:`histogram_lines`; the rooms' tick lags go into one
:class:`LagHistogram` for the relay (``posecast_tick_lag_seconds``).
"""

from __future__ import annotations

import math
from bisect import bisect_left
from collections.abc import Sequence
from dataclasses import dataclass, field

__all__ = ["TICK_LAG_BUCKETS", "LagHistogram", "bucket", "histogram_lines"]


#: Upper bounds (s) of the tick lag histogram's buckets (``posecast_tick_lag_seconds``;
#: one more bucket, +Inf, holds the rest).
TICK_LAG_BUCKETS = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0)


@dataclass
class LagHistogram:
    """Member ticks per lag bucket (``TICK_LAG_BUCKETS``, then +Inf; not cumulative),
    the lag measured from each member's due time, and the sum of those lags (s).
    One for the server, shared by its rooms."""

    counts: list[int] = field(default_factory=lambda: [0] * (len(TICK_LAG_BUCKETS) + 1))
    total: float = 0.0

    def observe(self, lag: float) -> None:
        lag = max(0.0, lag)
        self.counts[bisect_left(TICK_LAG_BUCKETS, lag)] += 1
        self.total += lag


def bucket(value: float, bounds: Sequence[float]) -> int:
    """The index of the first bound ``value`` is at or under (``len(bounds)``: +Inf)."""
    return next((i for i, b in enumerate(bounds) if value <= b), len(bounds))


def histogram_lines(
    name: str, help_text: str, bounds: Sequence[float], counts: Sequence[int], total: float
) -> list[str]:
    """Prometheus text of a histogram: ``counts`` per bucket of ``bounds`` then +Inf
    (not cumulative), and the sum of the values."""
    lines = [f"# HELP {name} {help_text}", f"# TYPE {name} histogram"]
    cumulative = 0
    for bound, count in zip((*bounds, math.inf), counts, strict=True):
        cumulative += count
        le = "+Inf" if math.isinf(bound) else f"{bound:g}"
        lines.append(f'{name}_bucket{{le="{le}"}} {cumulative}')
    return [*lines, f"{name}_sum {total:g}", f"{name}_count {cumulative}"]
