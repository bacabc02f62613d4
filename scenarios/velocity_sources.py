"""Which keyframe velocities a velocity interpolator gets: central vs causal estimates.

:func:`compare_velocity_sources` scores a velocity method (``motor-hermite``)
with keyframe velocities from each source on the same traces, rates and QoE
definitions as Table 1's ideal sweep (keyframes = newest native sample at each
send time, one-interval playout, velocities rounded to float16 as the wire
carries them), and returns the hands p50/p95 tip error per source and rate.

Run: ``posecast velocity-sources --traces traces:eval --rates 10,15,16,17,20,30``.
A source is ``central``, ``causal`` (the default causal estimator) or
``causal:SAMPLES,DEGREE`` (e.g. ``causal:2,1``, the backward difference).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from posecast.scenarios.network import VELOCITY_WIRE_DTYPE
from posecast.scenarios.qoe import evaluate_group, ideal_delay, ideal_log, summarize
from posecast.scenarios.traces import Trace

__all__ = ["DEFAULT_VELOCITY_SOURCE", "compare_velocity_sources", "source_velocities"]

F64 = np.ndarray

#: The keyframe velocities every offline experiment gives a velocity method
#: (``compare``, ``table1``): ``causal`` (past native samples only), what a live
#: sender (a tracker runtime, the bots) has at capture time.
DEFAULT_VELOCITY_SOURCE = "causal"


def source_velocities(trace: Trace, source: str = DEFAULT_VELOCITY_SOURCE) -> F64:
    """Velocities ``(N, S, 6)`` of ``trace`` from ``source``, rounded to float16 as on the wire.

    ``source``: ``central``, ``causal`` or ``causal:SAMPLES,DEGREE``.
    """
    if source.startswith("causal:"):
        try:
            samples, degree = (int(x) for x in source.split(":", 1)[1].split(","))
        except ValueError:
            raise ValueError(f"malformed source {source!r}; use causal:SAMPLES,DEGREE") from None
        v = trace.causal_velocities(samples, degree)
    else:
        v = trace.velocities_from(source)
    lim = float(np.finfo(VELOCITY_WIRE_DTYPE).max)
    out: F64 = np.clip(v, -lim, lim).astype(VELOCITY_WIRE_DTYPE).astype(np.float64)
    return out


def compare_velocity_sources(
    traces: Sequence[Trace],
    rates: Sequence[float],
    sources: Sequence[str],
    method: str = "motor-hermite",
) -> dict[str, dict[float, dict[str, float]]]:
    """``{source: {rate: {"tip_p50_mm", "tip_p95_mm"}}}`` of the hands, pooled over traces."""
    out: dict[str, dict[float, dict[str, float]]] = {}
    for source in sources:
        vels = [source_velocities(tr, source) for tr in traces]
        per_rate: dict[float, dict[str, float]] = {}
        for rate in rates:
            groups = []
            for tr, v in zip(traces, vels, strict=True):
                log = ideal_log(tr.times, tr.poses, rate, v)
                delay = ideal_delay(rate, tr.native_rate)
                groups.append(evaluate_group(tr, log, delay, [method]))
            hands = summarize(groups)[method]["hands"]
            per_rate[rate] = {k: hands[k] for k in ("tip_p50_mm", "tip_p95_mm")}
        out[source] = per_rate
    return out
