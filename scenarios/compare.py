"""Offline interpolator comparison on a trace (ideal network).

For each send rate, keyframes are the latest native sample at each send time
``t0 + k/rate``; every stream is reconstructed at the trace's native sample
times with each interpolator under one-interval playout, and scored with the
QoE definitions of :mod:`scenarios.qoe`. Velocity methods get the keyframe
velocities Table 1 gives them (:data:`scenarios.velocity_sources.DEFAULT_VELOCITY_SOURCE`:
causal, what a live sender has; float16 as the wire carries them), so
``compare`` and ``table1`` give the same figures for the same trace and rate.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from posecast.interp import info
from posecast.scenarios.qoe import evaluate_group, ideal_delay, ideal_log, summarize
from posecast.scenarios.traces import Trace, load_trace
from posecast.scenarios.velocity_sources import DEFAULT_VELOCITY_SOURCE, source_velocities

__all__ = ["Comparison", "compare_trace", "run_compare"]

#: ``{rate: {method: {device_class: {stat: value}}}}``
Comparison = dict[float, dict[str, dict[str, dict[str, float]]]]


def compare_trace(
    trace: Trace,
    rates: Sequence[float],
    methods: Sequence[str],
    velocity_source: str = DEFAULT_VELOCITY_SOURCE,
) -> Comparison:
    """QoE of each method at each rate on one trace, ideal network.

    Each method gets one-interval playout plus its own look-ahead (a window
    method waits one interval more for the keyframe after the bracket).
    Velocity methods get keyframe velocities from ``velocity_source``
    (:func:`~scenarios.velocity_sources.source_velocities`).
    """
    out: Comparison = {}
    needs = any(info(m).needs_velocity for m in methods)
    vel = source_velocities(trace, velocity_source) if needs else None
    for rate in rates:
        # Ideal link: a keyframe arrives the instant it is sent.
        log = ideal_log(trace.times, trace.poses, rate, vel)
        groups = []
        for m in methods:
            delay = ideal_delay(rate, trace.native_rate, info(m).lookahead)
            groups.append(evaluate_group(trace, log, delay, [m]))
        out[rate] = summarize(groups)
    return out


def run_compare(
    trace_path: str | Path, rates: Sequence[float], methods: Sequence[str]
) -> tuple[Trace, Comparison]:
    trace = load_trace(trace_path)
    return trace, compare_trace(trace, rates, methods)
