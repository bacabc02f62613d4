"""Rates as a Prometheus histogram: counts per bucket, kept by the relay's rate metrics.

``server.rates`` (auto rates) and ``server.view_rates`` (rates from an error
budget) each count the rates they choose in buckets (not cumulative) and write them
with :func:`histogram_lines`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

__all__ = ["bucket", "histogram_lines"]


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
