"""Reproduce the paper's Table 1 offline: equal-QoE update rates per network tier.

The paper claims that, for the same quality, its geometric-algebra methods need
20/10/7/5 updates/s where SoA needs 30/20/15/12 (33/50/53/58 % less bandwidth)
and 16.5 % less running time. :func:`run_table1` measures this on traces:

(a) **QoE curves**: for every method and rate (1 Hz steps), keyframes are the
    latest native sample at each send time ``t0 + k/r``; an ideal link delivers
    them at once and the receiver plays out one interval behind
    (:func:`scenarios.qoe.ideal_delay`). Errors are pooled over the traces per
    device class (:mod:`scenarios.qoe` is the one definition of every number).
(b) **Equal-QoE rates** per tier: SoA runs at the tier's rate (its
    ``max_rate_hz``, or less if the bandwidth cap cannot carry the room's
    snapshots at that rate); each method's equal-QoE rate is the lowest rate
    whose headline number (p95 tip error of the hands) is no worse than SoA's
    there (:func:`equal_qoe_rate`); bandwidth saving ``1 - r / r_soa``; and the
    receiver's CPU time (:func:`receiver_cpu_time`) at the two rates.
(c) The same through each tier's :class:`~scenarios.network.LinkModel`
    (latency, jitter, loss, bandwidth cap) with a **fixed** playout delay per
    run, ``D = 1/r + p95(keyframe age)`` where age = arrival - capture over the
    run's delivered keyframes (the steady state the live receiver's adaptive
    :class:`~client.playout.PlayoutDelay` converges to). Stalls and delay
    show up there. Through a link the equal-QoE rate is searched only up to
    the tier's rate (the tier allows no more). Every method sees the same link
    realisation at a given rate (one seed per tier, trace and rate).
(d) **Error versus latency** (key ``"frontier"``, beyond the paper): hands
    only, every method at a few rates (:data:`FRONTIER_RATES`) and playout
    delays ``D = (f + look-ahead)/rate + lag`` (:data:`FRONTIER_FRACTIONS`),
    each with three stall policies (:data:`VARIANTS`: hold, dead reckoning with
    the correction as a jump, dead reckoning with the correction blended in),
    on the ideal network and through each tier's link. Latency is
    capture-to-display, i.e. D itself (ages count from capture). From these
    points: the frontier (best headline within each latency budget), and per
    tier the fewest bytes/s each method needs for SoA's headline at SoA's
    latency (:func:`cheapest_point`).
(e) Writes ``table1.md``, ``table1.json`` and PNG plots to ``out_dir``.

Every interpolator kind is handled: each method plays out one interval plus
its look-ahead (``interp.info(m).lookahead``); methods that need keyframe
velocities get the trace's velocities (:data:`VELOCITY_SOURCE`: causal by
default, what a live sender has at capture time) rounded to float16 and the bigger wire
frame of the velocity variant (:func:`method_wire_bytes`), so savings are
reported in updates/s and in bytes/s. The receiver running time covers every
method; velocity methods decode velocity snapshots and render from the
velocities their buffers keep, as the live receiver does.

Run: ``posecast table1 --traces traces:dev --out DIR`` (see ``--help``), which
calls :func:`run_table1`.

The package: :mod:`~scenarios.table1.common` (constants, pure helpers),
:mod:`~scenarios.table1.sweep` (QoE against rate, ideal and through links),
:mod:`~scenarios.table1.runtime` (receiver running time),
:mod:`~scenarios.table1.frontier` (error versus latency),
:mod:`~scenarios.table1.report` (JSON and Markdown),
:mod:`~scenarios.table1.plots` (PNGs) and :mod:`~scenarios.table1.run` (the
pipeline).
"""

from posecast.scenarios.table1.common import (
    CORRECTION_TIME_S,
    CURVE_KEYS,
    DEFAULT_METHODS,
    DEFAULT_ROOM_POSES,
    EXTRAPOLATE_HORIZON_S,
    F64,
    FRONTIER_FRACTIONS,
    FRONTIER_RATES,
    HEADLINE,
    PAPER,
    VARIANTS,
    VELOCITY_SOURCE,
    Progress,
    Stats,
    describe_rates,
    equal_qoe_rate,
    keyframe_velocities,
    method_wire_bytes,
    resolve_traces,
    saving_pct,
    snapped_range,
    tier_rate,
)
from posecast.scenarios.table1.frontier import _refine as _refine
from posecast.scenarios.table1.frontier import _same_bracket as _same_bracket
from posecast.scenarios.table1.frontier import cheapest_point, pareto_frontier
from posecast.scenarios.table1.report import SNAPPED_RATE, SNAPPED_SAVING
from posecast.scenarios.table1.run import Table1Interrupted, run_table1
from posecast.scenarios.table1.runtime import _prepare_receiver as _prepare_receiver
from posecast.scenarios.table1.runtime import receiver_cpu_time, receiver_cpu_times
from posecast.scenarios.table1.sweep import _ideal_log as _ideal_log

__all__ = [
    "CORRECTION_TIME_S",
    "CURVE_KEYS",
    "DEFAULT_METHODS",
    "DEFAULT_ROOM_POSES",
    "EXTRAPOLATE_HORIZON_S",
    "F64",
    "FRONTIER_FRACTIONS",
    "FRONTIER_RATES",
    "HEADLINE",
    "PAPER",
    "SNAPPED_RATE",
    "SNAPPED_SAVING",
    "VARIANTS",
    "VELOCITY_SOURCE",
    "Progress",
    "Stats",
    "Table1Interrupted",
    "cheapest_point",
    "describe_rates",
    "equal_qoe_rate",
    "keyframe_velocities",
    "method_wire_bytes",
    "pareto_frontier",
    "receiver_cpu_time",
    "receiver_cpu_times",
    "resolve_traces",
    "run_table1",
    "saving_pct",
    "snapped_range",
    "tier_rate",
]
