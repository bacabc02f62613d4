"""Constants and pure helpers shared by the Table 1 stages (sweep, frontier, runtime, report)."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from posecast import interp
from posecast.scenarios.network import (
    VELOCITY_BYTES_PER_POSE,
    Tier,
    affordable_rate,
    wire_bytes,
)
from posecast.scenarios.synthetic import suite_traces, synthetic_motion
from posecast.scenarios.traces import Trace, TraceError, find_traces, load_trace
from posecast.scenarios.velocity_sources import DEFAULT_VELOCITY_SOURCE, source_velocities

F64 = NDArray[np.float64]
#: ``progress(stage, done, total)``.
Progress = Callable[[str, int, int], None]
#: ``{method: {device_class: {stat: value}}}``
Stats = dict[str, dict[str, dict[str, float]]]

DEFAULT_METHODS = ("soa", "dq-slerp", "motor-lerp")
#: The headline QoE number: p95 tip error of the hands (mm).
HEADLINE = ("hands", "tip_p95_mm")
#: The smoothness number beside it: p95 velocity error of the hands' tip (m/s).
SMOOTHNESS = ("hands", "vel_p95_mps")
CURVE_KEYS = (
    "pos_p50_mm",
    "pos_p95_mm",
    "rot_p50_deg",
    "rot_p95_deg",
    "tip_p50_mm",
    "tip_p95_mm",
    "vel_p50_mps",
    "vel_p95_mps",
)

#: The paper's Table 1 (rates in updates/s; the GA methods share one row).
PAPER: dict[str, Any] = {
    "source": (
        "Kamarianakis et al., 'Less Is More: Efficient Networked VR Transformation "
        "Handling Using Geometric Algebra', Table 1"
    ),
    "ga_methods": ["dq-slerp", "motor-lerp"],
    "tiers": [
        {"name": "excellent", "soa_rate": 30, "ga_rate": 20, "bandwidth_saving_pct": 33},
        {"name": "good", "soa_rate": 20, "ga_rate": 10, "bandwidth_saving_pct": 50},
        {"name": "mediocre", "soa_rate": 15, "ga_rate": 7, "bandwidth_saving_pct": 53},
        {"name": "poor", "soa_rate": 12, "ga_rate": 5, "bandwidth_saving_pct": 58},
    ],
    "running_time_saving_pct": 16.5,
}

#: Poses in one snapshot for wire sizes: a 16-user room, head + two hands each.
DEFAULT_ROOM_POSES = 48

#: Where velocity methods' keyframe velocities come from (one of
#: ``scenarios.traces.VELOCITY_SOURCES``): ``causal`` (past native samples only,
#: what the live bots send) or ``central`` (needs the next native sample).
VELOCITY_SOURCE = DEFAULT_VELOCITY_SOURCE

#: Error-versus-latency view: playout delay D = (f + look-ahead) / rate + lag for
#: these f (lag: one native frame on the ideal network, p95 keyframe age on a link).
FRONTIER_FRACTIONS = (0.25, 0.5, 0.75, 1.0, 1.5, 2.0)
#: Rates of the error-versus-latency view (those inside the run's rate range, plus
#: the tiers' SoA rates): the paper's and the tiers' rates. The integer rates in
#: between are bisected where a verdict needs them (see ``_refine``).
FRONTIER_RATES = (5, 7, 10, 12, 15, 20, 30)
#: Dead-reckoning horizon past the newest keyframe (s). Chosen on the dev traces
#: (25/50/100/200 ms tried at 10-20 Hz, ideal and poor link): 50 ms was best or
#: within 1 % of best for every method; longer horizons only add error.
EXTRAPOLATE_HORIZON_S = 0.05
#: Correction blend time of the smoothed variant (s): 3 render frames at 90 Hz.
#: An assumption, not tuned: blending only ever adds error to the headline (it
#: shows the stale prediction for longer); what it buys is continuity.
CORRECTION_TIME_S = 0.03
#: Playout variants of the view: hold on a stall (DESIGN.md), dead reckoning with
#: the correction applied at once (a jump), and dead reckoning with the
#: correction blended over CORRECTION_TIME_S.
VARIANTS = ("hold", "extrapolate", "smooth")


# ---------------------------------------------------------------- pure helpers


def equal_qoe_rate(
    headline: Mapping[int, float], reference: float, rates: Iterable[int] | None = None
) -> int | None:
    """Lowest rate whose headline error is no worse (<=) than ``reference``.

    ``headline`` maps rate -> headline error of one method; ``rates`` limits the
    search (default: every rate of ``headline``). ``None`` if no rate qualifies
    (NaN never qualifies).
    """
    candidates = sorted(headline if rates is None else (r for r in rates if r in headline))
    for r in candidates:
        v = headline[r]
        if not math.isnan(v) and not math.isnan(reference) and v <= reference:
            return int(r)
    return None


def snapped_range(rate: int | None, rates: Iterable[int]) -> tuple[int, int] | None:
    """Where the 1 Hz-step equal-QoE rate lies when ``rate`` was found on a sparse list.

    The equal-QoE rate is defined in 1 Hz steps; searched over ``rates`` with gaps,
    the rate found is the lowest *listed* rate that meets the bar, and the true
    one may be any integer rate above the listed rate below it. Returns
    ``(lowest, rate)``, the range it lies in, when ``rate`` was snapped up over
    such a gap; ``None`` when the rate just below ``rate`` was searched too, or
    ``rate`` is the lowest searched (or ``None``).
    """
    if rate is None:
        return None
    below = [int(r) for r in rates if int(r) < rate]
    if not below or max(below) == rate - 1:
        return None
    return max(below) + 1, int(rate)


def describe_rates(rates: Iterable[int]) -> str:
    """``10-30 Hz in 1 Hz steps`` for a contiguous range, else e.g. ``5-8, 10, 20 Hz``."""
    rs = sorted({int(r) for r in rates})
    if not rs:
        return "no rates"
    if len(rs) == 1:
        return f"{rs[0]} Hz"
    if rs[-1] - rs[0] == len(rs) - 1:
        return f"{rs[0]}-{rs[-1]} Hz in 1 Hz steps"
    runs: list[list[int]] = []
    for r in rs:
        if runs and r == runs[-1][-1] + 1:
            runs[-1].append(r)
        else:
            runs.append([r])
    parts: list[str] = []
    for run in runs:
        if len(run) >= 3:
            parts.append(f"{run[0]}-{run[-1]}")
        else:
            parts.extend(str(r) for r in run)
    return ", ".join(parts) + " Hz"


def _contiguous(rates: Sequence[int]) -> bool:
    return not rates or rates[-1] - rates[0] == len(rates) - 1


def saving_pct(value: float | None, reference: float | None) -> float | None:
    """``100 (1 - value / reference)``; ``None`` if either is missing."""
    if value is None or reference is None or reference == 0:
        return None
    if math.isnan(value) or math.isnan(reference):
        return None
    return 100.0 * (1.0 - value / reference)


def method_wire_bytes(method: str, room_poses: int = DEFAULT_ROOM_POSES) -> int:
    """Wire bytes of a room snapshot for ``method`` (velocity methods: the velocity variant)."""
    extra = VELOCITY_BYTES_PER_POSE if interp.info(method).needs_velocity else 0
    return wire_bytes(room_poses, extra)


def keyframe_velocities(trace: Trace, source: str | None = None) -> F64:
    """The trace's velocities ``(N, S, 6)`` as the velocity variant carries them (float16).

    ``source``: ``causal`` or ``central`` (default :data:`VELOCITY_SOURCE`).
    """
    out: F64 = source_velocities(trace, VELOCITY_SOURCE if source is None else source)
    return out


def tier_rate(tier: Tier, frame_bytes: float) -> int:
    """SoA's rate in a tier: its max rate, or less if the cap cannot carry it (1 Hz steps)."""
    return max(1, math.floor(affordable_rate(tier, frame_bytes) + 1e-9))


# ---------------------------------------------------------------- traces


def resolve_traces(spec: str | Path) -> list[Trace]:
    """Traces for ``traces:dev``/``traces:eval``, a CSV or directory of CSVs, or synthetic.

    ``synthetic`` is the packaged suite (``scenarios/data/synthetic.toml``); a
    ``.toml`` path is a suite file; ``synthetic:NAME`` or ``synthetic:NAME:SEED``
    is one synthetic motion with default parameters.
    """
    s = str(spec)
    if s == "synthetic":
        return suite_traces()
    if s.startswith("synthetic:"):
        _, name, seed = ([*s.split(":"), "0"])[:3]
        try:
            return [synthetic_motion(name, int(seed))]
        except ValueError:
            raise TraceError(f"malformed synthetic spec {s!r}; use synthetic:NAME[:SEED]") from None
    if s.endswith(".toml"):
        return suite_traces(s)
    return [load_trace(p) for p in find_traces(s)]


def _as_traces(traces: Sequence[str | Path | Trace]) -> list[Trace]:
    out: list[Trace] = []
    for item in traces:
        if isinstance(item, Trace):
            out.append(item)
        elif isinstance(item, Path):
            out.append(load_trace(item))
        else:
            out.extend(resolve_traces(item))
    if not out:
        raise TraceError("no traces given")
    return out
